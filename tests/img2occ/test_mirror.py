"""Mirrored scenes: the cameras of a mirrored batch see the mirrored world, targets follow."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import GridSpec
from renderworld.geometry import VoxelGrid
from renderworld.img2occ import Img2OccConfig
from renderworld.img2occ.backproject import backproject_labels
from renderworld.img2occ.mirror import mirror_batch, mirror_voxels
from tests.img2occ._synthetic import TEST_GRID, make_scene, ray_cast
from tests.img2occ.conftest import RENDER_SIZE, make_model


def test_mirrored_cameras_see_the_mirrored_scene(synthetic_batch):
    """Ray casting the y-flipped GT through the mirrored poses and intrinsics gives the
    left-right flipped depth and label maps of the original cameras."""
    mirrored = mirror_batch(synthetic_batch)
    occ = make_scene(TEST_GRID)
    h, w = RENDER_SIZE
    for c in range(6):
        pose = synthetic_batch["cam_to_ego"][0, c].double().numpy()
        k = synthetic_batch["render_intrinsics"][0, c].double().numpy()
        depth, labels, _ = ray_cast(occ, TEST_GRID, pose, k, w, h)
        m_pose = mirrored["cam_to_ego"][0, c].double().numpy()
        m_k = mirrored["render_intrinsics"][0, c].double().numpy()
        m_depth, m_labels, _ = ray_cast(occ[:, ::-1], TEST_GRID, m_pose, m_k, w, h)
        assert np.linalg.det(m_pose[:3, :3]) == pytest.approx(1.0, abs=1e-5)
        # Ray marching in 5 cm steps: a ray grazing a voxel face may stop one step apart.
        assert np.mean(np.abs(m_depth - depth[:, ::-1]) < 0.06) > 0.98, c
        assert np.mean(m_labels == labels[:, ::-1]) > 0.98, c


def test_backprojected_targets_of_the_mirror_are_the_mirrored_targets(synthetic_batch):
    grid = VoxelGrid(TEST_GRID)
    keys = ("depth", "semantics", "render_intrinsics", "cam_to_ego")
    plain = backproject_labels(*(synthetic_batch[k] for k in keys), grid)
    mirrored = mirror_batch(synthetic_batch)
    flipped = backproject_labels(*(mirrored[k] for k in keys), grid)
    assert plain.ne(255).sum() > 0
    same = mirror_voxels(flipped, TEST_GRID.shape) == plain
    assert same.float().mean() > 0.995  # points exactly on a voxel face may round apart


def test_mirroring_twice_gives_the_batch_back_and_leaves_the_input_alone(synthetic_batch):
    before = {k: v.clone() for k, v in synthetic_batch.items() if torch.is_tensor(v)}
    twice = mirror_batch(mirror_batch(synthetic_batch))
    for key, value in before.items():
        torch.testing.assert_close(twice[key], value, msg=key)
        torch.testing.assert_close(synthetic_batch[key], value, msg=key)
    once = mirror_batch(synthetic_batch)
    torch.testing.assert_close(once["occ"], synthetic_batch["occ"].flip(2))
    torch.testing.assert_close(once["images"], synthetic_batch["images"].flip(-1))


def test_unknown_keys_and_asymmetric_grids_fail_clearly(synthetic_batch):
    with pytest.raises(ValueError, match=r"no mirroring rule for batch key\(s\) \['lidar'\]"):
        mirror_batch({**synthetic_batch, "lidar": torch.zeros(3)})
    batch = {k: v for k, v in synthetic_batch.items() if k != "images"}
    with pytest.raises(ValueError, match="'intrinsics' needs 'images'"):
        mirror_batch(batch)
    skewed = GridSpec("skewed", (0.0, -4.0, -1.0), (8.0, 6.0, 3.0), (8, 10, 4))
    with pytest.raises(ValueError, match=r"mirror_prob / mirror_readout: grid 'skewed'"):
        Img2OccConfig(grid=skewed, mirror_prob=0.5)
    with pytest.raises(ValueError, match="mirror_prob: expected a value in"):
        Img2OccConfig(grid=TEST_GRID, mirror_prob=1.5)


def test_mirror_readout_averages_the_scene_and_its_mirror(synthetic_batch):
    model = make_model(mirror_readout=True).eval()
    plain = make_model().eval()
    plain.load_state_dict(model.state_dict())
    shape = TEST_GRID.shape
    with torch.no_grad():
        got = model(synthetic_batch, render=False).gaussians
        a = plain(synthetic_batch, render=False).gaussians
        b = plain(mirror_batch(synthetic_batch), render=False).gaussians
    expected_op = 0.5 * (a.opacities + mirror_voxels(b.opacities, shape))
    torch.testing.assert_close(got.opacities, expected_op)
    expected_p = 0.5 * (a.logits.softmax(-1) + mirror_voxels(b.logits, shape).softmax(-1))
    torch.testing.assert_close(got.logits.softmax(-1), expected_p)
    # Training forward (and rendering) stays a single pass.
    model.train()
    assert model(synthetic_batch, render=False).gaussians.opacities.requires_grad


def test_training_mirrors_with_mirror_prob_and_stays_finite(synthetic_batch):
    model = make_model(mirror_prob=1.0)
    model.eval()
    assert model.augment(synthetic_batch) is synthetic_batch
    model.train()
    batch = model.augment(synthetic_batch)
    torch.testing.assert_close(batch["depth"], synthetic_batch["depth"].flip(-1))
    loss, _ = model.loss(batch, model(batch))
    loss.backward()
    assert torch.isfinite(loss)
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert make_model(mirror_prob=0.0).train().augment(synthetic_batch) is synthetic_batch
