"""Back-projected voxel targets: by hand, against the synthetic scene's GT, inside the model."""

from __future__ import annotations

import pytest
import torch

from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES, OCC3D_CLASSES, GridSpec
from renderworld.geometry import VoxelGrid
from renderworld.img2occ.backproject import (
    STATIC_CLASS_IDS,
    backproject_labels,
    backprojected_loss,
)
from tests.img2occ._synthetic import TEST_GRID
from tests.img2occ.conftest import make_model, tiny_config
from tests.img2occ.test_model import _hard_case

# Camera looking along ego +x from (0, 0, 1): camera x → ego -y, y → ego -z, z → ego +x.
_FORWARD = torch.tensor(
    [[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]]
)
# 1 m voxels, x in [0, 8), y in [-4, 4), z in [-1, 3): a point at ego (x, y, z) lands in
# voxel (floor(x), floor(y + 4), floor(z + 1)).
_GRID = VoxelGrid(GridSpec("t", (0.0, -4.0, -1.0), (8.0, 4.0, 3.0), (8, 8, 4)))
CAR = OCC3D_CLASSES.index("car")
ROAD = OCC3D_CLASSES.index("driveable_surface")


def _wall(h: int = 2, w: int = 4, depth: float = 5.5) -> tuple[torch.Tensor, ...]:
    """A 2x4 depth map of a wall at camera z = depth, f = 2 px: pixel columns at u = 0.5..3.5
    look at camera x = (u - 2) / 2 · z, rows at v = 0.5, 1.5 at camera y = (v - 1) / 2 · z."""
    d = torch.full((1, 1, h, w), depth)
    k = torch.tensor([[2.0, 0.0, w / 2], [0.0, 2.0, h / 2], [0.0, 0.0, 1.0]]).view(1, 1, 3, 3)
    return d, k, _FORWARD.view(1, 1, 4, 4)


def _index(x: float, y: float, z: float) -> int:
    i, j, k = int(x), int(y + 4), int(z + 1)
    return (i * 8 + j) * 4 + k


def test_a_labelled_wall_lands_in_its_voxels_with_its_classes():
    depth, intr, pose = _wall()
    sem = torch.tensor([[[[CAR, CAR, ROAD, ROAD], [CAR, CAR, ROAD, ROAD]]]])
    out = backproject_labels(depth, sem, intr, pose, _GRID)
    assert out.shape == (1, 8 * 8 * 4)
    # Columns u = 0.5, 1.5 (car) sit at camera x = -4.125, -1.375 → ego y = 4.125 (outside
    # the grid), 1.375; columns 2.5, 3.5 (road) at ego y = -1.375, -4.125 (outside). Rows
    # v = 0.5, 1.5 at camera y = -1.375, 1.375 → ego z = 2.375, -0.375. All at ego x = 5.5.
    expected = torch.full((8 * 8 * 4,), FREE_ID)
    for y, cls in ((1.375, CAR), (-1.375, ROAD)):
        for z in (2.375, -0.375):
            expected[_index(5.5, y, z)] = cls
    torch.testing.assert_close(out[0], expected)


def test_most_frequent_class_wins_and_ties_go_to_the_lower_id():
    # f = 2, cx = 0, cy = 1: pixels u = 0.5, 1.5, 2.5 of row 0 at z = 0.5 m are the ego points
    # x = 0.5, y = -0.125, -0.375, -0.625, z = 1.125: all in one voxel.
    intr = torch.tensor([[2.0, 0.0, 0.0], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]]).view(1, 1, 3, 3)
    pose = _FORWARD.view(1, 1, 4, 4)
    voxel = _index(0.5, -0.5, 1.125)
    for labels, want in (((CAR, ROAD), CAR), ((ROAD, CAR), CAR), ((ROAD, CAR, ROAD), ROAD)):
        sem = torch.tensor(labels).view(1, 1, 1, -1)
        depth = torch.full(sem.shape, 0.5)
        out = backproject_labels(depth, sem, intr, pose, _GRID)
        assert int(out[0, voxel]) == want
        assert int((out != FREE_ID).sum()) == 1


def test_unlabelled_pixels_missing_depth_and_filtered_classes_count_nothing():
    depth, intr, pose = _wall()
    sem = torch.full((1, 1, 2, 4), CAR)
    sem[..., 1] = 255  # no label
    sem[..., 0, 2] = FREE_ID  # "free" is not a point's class
    depth[..., 1, 2] = 0.0  # labelled but without depth
    out = backproject_labels(depth, sem, intr, pose, _GRID)
    assert int((out != FREE_ID).sum()) == 0  # what is left falls outside the grid or is gone
    sem = torch.tensor([[[[CAR, CAR, ROAD, ROAD], [CAR, CAR, ROAD, ROAD]]]])
    depth, intr, pose = _wall()
    only_static = backproject_labels(depth, sem, intr, pose, _GRID, classes=STATIC_CLASS_IDS)
    assert set(only_static.unique().tolist()) == {ROAD, FREE_ID}
    assert CAR not in STATIC_CLASS_IDS and ROAD in STATIC_CLASS_IDS


def test_backprojection_validates_shapes():
    depth, intr, pose = _wall()
    sem = torch.zeros(1, 1, 2, 4, dtype=torch.long)
    with pytest.raises(ValueError, match="semantics"):
        backproject_labels(depth, sem[..., :3], intr, pose, _GRID)
    with pytest.raises(ValueError, match="intrinsics/cam_to_ego"):
        backproject_labels(depth, sem, intr, pose[..., :3, :], _GRID)


def test_the_synthetic_scenes_lidar_points_agree_with_its_gt(synthetic_batch):
    # The maps were ray-cast from the GT scene: every labelled point lies on the face of a
    # GT voxel of its class, so the voxel it falls in (the one behind the face, or the
    # free one in front when floor rounds outward) must be that class or free.
    b = synthetic_batch
    g = VoxelGrid(TEST_GRID)
    out = backproject_labels(
        b["depth"], b["semantics"], b["render_intrinsics"], b["cam_to_ego"], g
    )[0]
    gt = b["occ"][0].reshape(-1).long()
    hit = out != FREE_ID
    assert int(hit.sum()) > 20
    agree = (out[hit] == gt[hit]).float().mean().item()
    assert agree > 0.9, agree  # measured 1.0 (150 voxels)
    assert ((out[hit] == gt[hit]) | (gt[hit] == FREE_ID)).all()


def test_loss_targets_hits_occupied_and_seen_through_voxels_free():
    depth, intr, pose = _wall(depth=5.5)
    sem = torch.full((1, 1, 2, 4), ROAD)
    grid = _GRID
    centres = torch.as_tensor(grid.centres(), dtype=torch.float32).view(-1, 3)
    v = centres.shape[0]
    opac = torch.full((1, v), 0.5, requires_grad=True)
    logits = torch.zeros(1, v, NUM_SEMANTIC_CLASSES, requires_grad=True)
    batch = dict(depth=depth, semantics=sem, render_intrinsics=intr, cam_to_ego=pose)
    bce, ce, targets = backprojected_loss(opac, logits, centres, grid, batch, 1.0, 0.1)
    assert int(targets[0, _index(5.5, 1.375, -0.375)]) == ROAD
    assert int(targets[0, _index(2.5, 0.0, 1.0)]) == FREE_ID  # on a ray, 3 m before the wall
    assert int(targets[0, _index(7.5, 0.0, 1.0)]) == -1  # behind the wall: unknown
    assert bce.item() == pytest.approx(torch.log(torch.tensor(2.0)).item(), rel=1e-5)
    (bce + ce).backward()
    assert torch.isfinite(opac.grad).all() and opac.grad.abs().sum() > 0
    # Adjacent frames: their static points fill voxels the keyframe left empty; a car's not.
    adj_sem = torch.tensor([[[[CAR, CAR, ROAD, ROAD], [CAR, CAR, ROAD, ROAD]]]])
    adj_pose = pose.clone()
    adj_pose[..., 0, 3] = -2.0  # two metres behind: its wall at ego x = 3.5
    batch.update(
        adj_depth=depth, adj_semantics=adj_sem, adj_render_intrinsics=intr, adj_cam_to_ego=adj_pose
    )
    _, _, t2 = backprojected_loss(opac, logits, centres, grid, batch, 1.0, 0.1, adjacent=True)
    assert int(t2[0, _index(3.5, -1.375, -0.375)]) == ROAD
    assert int(t2[0, _index(3.5, 1.375, -0.375)]) != CAR
    _, _, t3 = backprojected_loss(opac, logits, centres, grid, batch, 1.0, 0.1, adjacent=False)
    assert int(t3[0, _index(3.5, -1.375, -0.375)]) != ROAD


def test_model_with_backprojection_trains_finite_on_hard_cases(synthetic_batch):
    model = make_model("torch", backproject_weight=1.0)
    model.train()
    for case in ("all_free_targets", "no_lidar_at_all", "zero_images", "cameras_without_lidar"):
        batch = _hard_case(synthetic_batch, case)
        out = model(batch)
        loss, logs = model.loss(batch, out)
        assert torch.isfinite(loss), logs
        assert "loss_bp_occ" in logs
        loss.backward()
        for name, p in model.named_parameters():
            assert p.grad is None or torch.isfinite(p.grad).all(), name
        model.zero_grad()


def test_backprojection_config_is_validated():
    with pytest.raises(ValueError, match="backproject_weight"):
        tiny_config(backproject_weight=-1.0)
    with pytest.raises(ValueError, match="backproject_adjacent: expected a bool"):
        tiny_config(backproject_adjacent="yes")
    with pytest.raises(ValueError, match="backproject_class_balance"):
        tiny_config(backproject_class_balance=2.0)


def test_class_balance_lifts_the_rare_class_voxels_gradient():
    depth, intr, pose = _wall(depth=5.5)
    sem = torch.tensor([[[[CAR, CAR, ROAD, ROAD], [ROAD, ROAD, ROAD, ROAD]]]])
    grid = _GRID
    centres = torch.as_tensor(grid.centres(), dtype=torch.float32).view(-1, 3)
    batch = dict(depth=depth, semantics=sem, render_intrinsics=intr, cam_to_ego=pose)
    car, road = _index(5.5, 1.375, 2.375), _index(5.5, -1.375, 2.375)
    ratios = []
    for p in (0.0, 0.5):
        opac = torch.full((1, centres.shape[0]), 0.5, requires_grad=True)
        logits = torch.zeros(1, centres.shape[0], NUM_SEMANTIC_CLASSES)
        bce, _, t = backprojected_loss(opac, logits, centres, grid, batch, 1.0, 0.1, False, 1e-6, p)
        assert int(t[0, car]) == CAR and int(t[0, road]) == ROAD
        bce.backward()
        assert torch.isfinite(opac.grad).all()
        ratios.append(float(opac.grad[0, car] / opac.grad[0, road]))
    assert ratios[0] == pytest.approx(1.0)  # unweighted: every target voxel alike
    assert ratios[1] > 1.5  # 1 car voxel vs 3 road voxels: sqrt(3) with p = 0.5
    assert ratios[1] == pytest.approx(3**0.5, rel=1e-4)
