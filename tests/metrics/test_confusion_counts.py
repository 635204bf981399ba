"""One counting rule for every confusion of the package: same counts everywhere, labels checked."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.img2occ.calibration import ReadoutCalibration
from renderworld.img2occ.readout import confusion_matrix as readout_confusion
from renderworld.metrics import ForecastMetric, OccupancyMetric
from renderworld.metrics.occupancy import confusion_counts, confusion_matrix
from renderworld.tokenizer.metrics import ConfusionMeter
from renderworld.tokenizer.metrics import confusion_matrix as tokenizer_confusion
from renderworld.training.stages.common import confusion_stats

N = NUM_OCC3D_CLASSES


def _reference(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Voxel-by-voxel count, independent of bincount."""
    out = np.zeros((N, N), dtype=np.int64)
    keep = np.ones(gt.shape, bool) if mask is None else mask
    np.add.at(out, (gt[keep].astype(np.int64), pred[keep].astype(np.int64)), 1)
    return out


@pytest.fixture
def labels():
    rng = np.random.default_rng(0)
    pred = rng.integers(0, N, size=(2, 20, 20, 4)).astype(np.uint8)
    gt = rng.integers(0, N, size=pred.shape).astype(np.uint8)
    mask = rng.random(pred.shape) < 0.6
    return pred, gt, mask


@pytest.mark.parametrize("masked", [False, True])
def test_every_caller_counts_the_same_on_valid_labels(labels, masked):
    pred, gt, mask = labels
    m = mask if masked else None
    tm = None if m is None else torch.from_numpy(m)
    tp, tg = torch.from_numpy(pred), torch.from_numpy(gt)
    ref = _reference(pred, gt, m)

    np.testing.assert_array_equal(confusion_matrix(pred, gt, m), ref)
    np.testing.assert_array_equal(confusion_matrix(tp, tg, tm), ref)
    np.testing.assert_array_equal(readout_confusion(pred, gt, m), ref)
    torch_counts = confusion_counts(tp, tg, tm)
    assert isinstance(torch_counts, torch.Tensor) and torch_counts.dtype == torch.int64
    np.testing.assert_array_equal(torch_counts.numpy(), ref)
    np.testing.assert_array_equal(tokenizer_confusion(tp, tg, tm).numpy(), ref)
    stats = confusion_stats(tp, tg, tm)
    assert stats.dtype == torch.float64
    np.testing.assert_array_equal(stats.numpy(), ref.astype(np.float64))
    meter = ConfusionMeter()
    meter.update(tp, tg, tm)
    np.testing.assert_array_equal(meter.conf.numpy(), ref)
    metric = OccupancyMetric(mask_name=None if m is None else "camera")
    metric.update(pred, gt, m)
    np.testing.assert_array_equal(metric.confusion, ref)


def test_a_uint8_mask_counts_like_the_bool_mask(labels):
    pred, gt, mask = labels
    tp, tg = torch.from_numpy(pred), torch.from_numpy(gt)
    ref = _reference(pred, gt, mask)
    np.testing.assert_array_equal(confusion_counts(tp, tg, torch.from_numpy(mask).byte()), ref)
    np.testing.assert_array_equal(confusion_counts(pred, gt, mask.astype(np.uint8)), ref)


def test_calibration_counts_like_the_metric():
    rng = np.random.default_rng(1)
    v = 500
    op = torch.from_numpy(rng.random(v).astype(np.float32))
    logits = torch.from_numpy(rng.normal(size=(v, FREE_ID)).astype(np.float32))
    gt = torch.from_numpy(rng.integers(0, N, size=v))
    cal = ReadoutCalibration(thresholds=[0.3, 0.5])
    cal.update(op, logits, gt)
    offsets, thresholds = torch.zeros(FREE_ID), torch.full((FREE_ID,), 0.5)
    cls = logits.argmax(-1)
    pred = torch.where(op > 0.5, cls, torch.full_like(cls, FREE_ID))
    ref = _reference(pred.numpy(), gt.numpy(), None)
    np.testing.assert_array_equal(cal.confusion(offsets, thresholds).numpy(), ref)


def _t(*arrays):
    return [torch.from_numpy(a) for a in arrays]


# Every path that counted a confusion before the counting rule had one home: (argument name the
# caller gives the GT, call).
CALLERS = {
    "confusion_matrix": ("gt", lambda p, g, m: confusion_matrix(p, g, m)),
    "confusion_counts": ("gt", lambda p, g, m: confusion_counts(*_t(p, g, m))),
    "readout": ("gt", lambda p, g, m: readout_confusion(p, g, m)),
    "OccupancyMetric": ("gt", lambda p, g, m: OccupancyMetric("camera").update(*_t(p, g, m))),
    "ForecastMetric": (  # [B=2, S=20, X=20, Y=4, Z=1]: every future step is checked
        "gt",
        lambda p, g, m: ForecastMetric(steps=20, mask_name="camera").update(
            *_t(p[..., None], g[..., None], m[..., None])
        ),
    ),
    "confusion_stats": ("gt", lambda p, g, m: confusion_stats(*_t(p, g, m))),
    "confusion_stats_unmasked": ("gt", lambda p, g, m: confusion_stats(*_t(p, g))),
    "tokenizer": ("target", lambda p, g, m: tokenizer_confusion(*_t(p, g, m))),
    "ConfusionMeter": ("target", lambda p, g, m: ConfusionMeter().update(*_t(p, g, m))),
}


@pytest.mark.parametrize("caller", sorted(CALLERS))
@pytest.mark.parametrize("which, value", [("pred", 18), ("pred", -1), ("gt", 18), ("gt", 255)])
def test_out_of_range_labels_are_rejected_in_every_caller(labels, caller, which, value):
    pred, gt, mask = labels[0].astype(np.int64), labels[1].astype(np.int64), labels[2].copy()
    (pred if which == "pred" else gt).flat[7] = value
    mask.flat[7] = False  # a masked-out voxel is checked too: the labels are wrong, not ignored
    gt_name, call = CALLERS[caller]
    name = gt_name if which == "gt" else "pred"
    with pytest.raises(ValueError, match=rf"{name}: expected labels in \[0, 17\]"):
        call(pred, gt, mask)


def test_calibration_rejects_an_out_of_range_gt():
    v = 50
    cal = ReadoutCalibration(thresholds=[0.3])
    gt = torch.zeros(v, dtype=torch.int64)
    gt[3] = 18
    op = torch.ones(v)  # live voxels: checked when the fit counts them
    cal.update(op, torch.zeros(v, FREE_ID), gt)
    with pytest.raises(ValueError, match=r"gt: expected labels in \[0, 17\], got \[0, 18\]"):
        cal.fit()
    dead = ReadoutCalibration(thresholds=[0.3])  # always-free voxels: checked on update
    with pytest.raises(ValueError, match=r"gt: expected labels in \[0, 17\]"):
        dead.update(torch.zeros(v), torch.zeros(v, FREE_ID), gt)


def test_a_mask_that_is_not_zero_or_one_is_rejected(labels):
    pred, gt, mask = labels
    bad = mask.astype(np.uint8)
    bad.flat[3] = 2
    with pytest.raises(ValueError, match="mask: expected bool or 0/1"):
        confusion_counts(torch.from_numpy(pred), torch.from_numpy(gt), torch.from_numpy(bad))
    with pytest.raises(ValueError, match="mask: expected bool or 0/1"):
        confusion_matrix(pred, gt, bad)
