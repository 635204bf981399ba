"""Readout calibration: per-class logit offsets with the per-class thresholds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, OCC3D_CLASSES
from renderworld.img2occ import choose_threshold
from renderworld.img2occ.calibration import ReadoutCalibration
from renderworld.img2occ.readout import readout_occupancy
from renderworld.metrics.occupancy import confusion_matrix, mean_iou
from tests.img2occ._synthetic import TEST_GRID
from tests.img2occ.conftest import make_model

BARRIER = OCC3D_CLASSES.index("barrier")
ROAD = OCC3D_CLASSES.index("driveable_surface")
CAR = OCC3D_CLASSES.index("car")
K = FREE_ID
THRESHOLDS = (0.1, 0.3, 0.5, 0.7, 0.9)


def _stealing_case(n: int = 400, seed: int = 0):
    """Road voxels where barrier wins the argmax by a small margin (30 %), true barrier and
    car voxels with clear logits, free voxels of low opacity: a barrier offset of about -0.5
    reads everything right, no threshold can."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.full((n,), ROAD)
    gt[: n // 10] = BARRIER
    gt[n // 10 : n // 5] = CAR
    gt[-n // 4 :] = FREE_ID
    logits = torch.randn(n, K, generator=g) * 0.1 - 2.0
    occupied = gt != FREE_ID
    logits[occupied, gt[occupied]] = 3.0
    steal = (gt == ROAD) & (torch.rand(n, generator=g) < 0.3)
    logits[steal, BARRIER] = 3.2
    opac = torch.where(occupied, 0.8, 0.05) + 0.01 * torch.rand(n, generator=g)
    return opac[None], logits[None], gt[None]


def test_offsets_undo_a_class_that_steals_the_argmax():
    op, lg, gt = _stealing_case()
    cal = ReadoutCalibration(THRESHOLDS, rounds=2)
    cal.update(op, lg, gt)
    offsets, thresholds, history = cal.fit()
    assert history[0] < 0.8  # thresholds alone: barrier's IoU stays low
    assert history[-1] == pytest.approx(1.0)
    assert all(b >= a - 1e-12 for a, b in zip(history, history[1:]))
    assert -3.0 <= float(offsets[BARRIER]) - float(offsets[ROAD]) < -0.2
    pred = readout_occupancy(op, lg, thresholds, (1, 1, op.shape[1]), offsets).view(1, -1)
    assert mean_iou(confusion_matrix(pred, gt)) == pytest.approx(1.0)


def test_confusion_matches_the_readout_oracle_including_pruned_voxels():
    """The stored live voxels plus the always-free counts give exactly the confusion of the
    plain readout over every voxel, for any offsets and thresholds."""
    g = torch.Generator().manual_seed(1)
    cal = ReadoutCalibration(THRESHOLDS)
    batches = []
    for _ in range(3):
        op = torch.rand(2, 300, generator=g)
        lg = torch.randn(2, 300, K, generator=g)
        gt = torch.randint(0, FREE_ID + 1, (2, 300), generator=g)
        mask = torch.rand(2, 300, generator=g) < 0.7
        cal.update(op, lg, gt, mask)
        batches.append((op, lg, gt, mask))
    for trial in range(3):
        offsets = torch.randn(K, generator=g) * (trial > 0)
        thresholds = torch.tensor(THRESHOLDS)[torch.randint(0, 5, (K,), generator=g)]
        expected = np.zeros((FREE_ID + 1, FREE_ID + 1), dtype=np.int64)
        for op, lg, gt, mask in batches:
            pred = readout_occupancy(op, lg, thresholds, (1, 300, 1), offsets).view(2, 300)
            expected += confusion_matrix(pred, gt, mask)
        np.testing.assert_array_equal(cal.confusion(offsets, thresholds).numpy(), expected)


def test_a_class_absent_from_gt_is_never_predicted_rather_than_scored_zero():
    op, lg, gt = _stealing_case()
    lg = lg.clone()
    lg[0, :5, CAR] = 5.0  # five free voxels lean to car, but only at opacity 0.05
    gt = gt.clone()
    gt[gt == CAR] = ROAD  # car is absent from the GT
    op = op.clone()
    op[0, :40] = 0.6
    cal = ReadoutCalibration(THRESHOLDS)
    cal.update(op, lg, gt)
    offsets, thresholds, _ = cal.fit()
    pred = readout_occupancy(op, lg, thresholds, (1, 1, op.shape[1]), offsets)
    assert not bool((pred == CAR).any())


def test_choose_threshold_stores_offsets_that_the_readout_uses(synthetic_batch):
    model = make_model().eval()
    with torch.no_grad():
        # Untrained head biased so that barrier wins every voxel's argmax by 0.5 over road:
        # no threshold can read the ground right, an offset can.
        bias = model.head.out.bias.view(TEST_GRID.shape[2], -1)
        bias[:, 10] = 2.0  # opacity ~0.88 everywhere
        bias[:, 11 + ROAD] = 1.0
        bias[:, 11 + BARRIER] = 1.5
        model.set_class_offsets(torch.full((K,), 0.7))  # reset to 0 before calibrating
        choose_threshold(model, [synthetic_batch], THRESHOLDS, per_class=True, class_offsets=True)
        pred = model.readout(model(synthetic_batch, render=False))
        cal = ReadoutCalibration(THRESHOLDS)
        g = model(synthetic_batch, render=False).gaussians
        cal.update(g.opacities, g.logits, synthetic_batch["occ"], synthetic_batch["mask_camera"])
        _, _, history = cal.fit()
    conf = confusion_matrix(pred, synthetic_batch["occ"], synthetic_batch["mask_camera"])
    assert mean_iou(conf) == pytest.approx(history[-1])
    # The fit moved some offset, so the equality above needs the stored offsets in readout.
    assert bool((model.class_offsets != 0).any()) and history[-1] > history[0]
    assert set(model.class_offsets.tolist()) <= {-3, -2, -1.5, -1, -0.5, -0.25, 0, 0.25, 0.5, 1,
                                                  1.5, 2, 3}  # fmt: skip


def test_old_state_without_offsets_loads_as_plain_argmax_and_bad_input_fails():
    model = make_model()
    state = {k: v for k, v in model.state_dict().items() if k != "class_offsets"}
    fresh = make_model()
    fresh.class_offsets.fill_(1.0)
    fresh.load_state_dict(state, strict=True)
    assert bool((fresh.class_offsets == 0).all())
    with pytest.raises(ValueError, match="offsets: expected 17 finite values"):
        model.set_class_offsets([float("nan")] * K)
    with pytest.raises(ValueError, match="class_offsets: needs per_class"):
        choose_threshold(model, [], class_offsets=True)
    with pytest.raises(ValueError, match="offsets: expected finite candidates including 0"):
        ReadoutCalibration(THRESHOLDS, offsets=(-1.0, 1.0))
    with pytest.raises(ValueError, match="no batch was added"):
        ReadoutCalibration(THRESHOLDS).fit()
