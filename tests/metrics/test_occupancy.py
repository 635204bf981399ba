import math

import numpy as np
import pytest
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.metrics import (
    OccupancyMetric,
    confusion_matrix,
    geometry_iou,
    iou_per_class,
    mean_iou,
)


def test_confusion_hand_case():
    gt = np.array([4, 4, 4, FREE_ID, 11, 11])
    pred = np.array([4, 4, FREE_ID, 4, 11, 13])
    c = confusion_matrix(pred, gt)
    assert c.shape == (NUM_OCC3D_CLASSES, NUM_OCC3D_CLASSES) and c.sum() == 6
    assert c[4, 4] == 2 and c[4, FREE_ID] == 1 and c[FREE_ID, 4] == 1
    assert c[11, 11] == 1 and c[11, 13] == 1
    iou = iou_per_class(c)
    assert iou[4] == pytest.approx(2 / 4)  # TP 2, FN 1, FP 1
    assert iou[11] == pytest.approx(1 / 2)
    assert iou[13] == 0.0  # predicted but absent in GT: counts as 0, not NaN
    assert iou[FREE_ID] == 0.0
    assert math.isnan(iou[0])  # neither GT nor prediction: NaN, left out of the mean
    assert mean_iou(c) == pytest.approx((0.5 + 0.5 + 0.0) / 3)
    # Occupied: gt {4,4,4,11,11} pred {4,4,4,11,13}: TP 4 (occupied both), FP 1, FN 1.
    assert geometry_iou(c) == pytest.approx(4 / 6)


def test_free_is_in_the_confusion_but_not_in_the_mean():
    gt = np.array([4, FREE_ID, FREE_ID, FREE_ID])
    pred = np.array([4, FREE_ID, 4, FREE_ID])
    c = confusion_matrix(pred, gt)
    assert iou_per_class(c)[FREE_ID] == pytest.approx(2 / 3)
    assert mean_iou(c) == pytest.approx(1 / 2)  # only class 4; free's IoU does not enter


def test_perfect_and_empty_cases():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, NUM_OCC3D_CLASSES, size=(3, 6, 6, 2)).astype(np.uint8)
    c = confusion_matrix(gt, gt)
    assert mean_iou(c) == 1.0 and geometry_iou(c) == 1.0
    all_free = np.full((4, 4, 2), FREE_ID, dtype=np.uint8)
    c = confusion_matrix(all_free, all_free)
    assert math.isnan(mean_iou(c)) and math.isnan(geometry_iou(c))
    # Predict everything free on a scene with objects: every present class scores 0.
    c = confusion_matrix(np.full_like(gt, FREE_ID), gt)
    assert mean_iou(c) == 0.0 and geometry_iou(c) == 0.0


def test_mask_and_torch_inputs():
    gt = torch.tensor([[4, 4], [FREE_ID, 11]], dtype=torch.uint8)
    pred = torch.tensor([[4, 0], [FREE_ID, 11]], dtype=torch.uint8)
    mask = torch.tensor([[True, False], [True, True]])
    c = confusion_matrix(pred, gt, mask)
    assert c.sum() == 3 and c[4, 0] == 0
    assert mean_iou(c) == 1.0
    assert confusion_matrix(pred, gt, mask.to(torch.uint8)).sum() == 3
    assert confusion_matrix(pred, gt, torch.zeros_like(mask)).sum() == 0  # empty mask: zeros


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(pred=np.array([18]), gt=np.array([0])), r"pred: expected labels in \[0, 17\]"),
        (dict(pred=np.array([0]), gt=np.array([-1])), r"gt: expected labels in \[0, 17\]"),
        (dict(pred=np.array([0.0]), gt=np.array([0])), "pred: expected integer class labels"),
        (dict(pred=np.array([0, 1]), gt=np.array([0])), "pred: expected the shape of gt"),
        (dict(pred=np.array([0]), gt=np.array([0]), mask=np.array([2])), "mask: expected bool"),
    ],
)
def test_confusion_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        confusion_matrix(**kwargs)


def test_metric_accumulates_over_the_split_not_per_sample():
    # Sample A: car TP 1 of union 1; sample B: car TP 0 of union 3. Split IoU = 1/4, not 0.5.
    m = OccupancyMetric()
    m.update(np.array([4]), np.array([4]))
    m.update(np.array([4, 4, FREE_ID]), np.array([FREE_ID, FREE_ID, 4]))
    r = m.compute()
    assert r["iou_per_class"]["car"] == pytest.approx(0.25)
    assert r["miou"] == pytest.approx(0.25)
    assert math.isnan(r["iou_per_class"]["bus"])
    assert r["region"] == "full volume" and "nanmean over classes 0..16" in r["protocol"]
    assert "full volume" in m.format_table() and "nanmean" in m.format_table()


def test_metric_merge_equals_single_accumulation():
    rng = np.random.default_rng(1)
    batches = [
        (
            rng.integers(0, 18, (4, 4, 2)),
            rng.integers(0, 18, (4, 4, 2)),
            rng.random((4, 4, 2)) > 0.3,
        )
        for _ in range(4)
    ]
    whole, a, b = (OccupancyMetric(mask_name="camera") for _ in range(3))
    for i, (p, g, mk) in enumerate(batches):
        whole.update(p, g, mk)
        (a if i % 2 else b).update(p, g, mk)
    a.merge(b)
    np.testing.assert_array_equal(a.confusion, whole.confusion)
    assert a.compute()["region"] == "inside the camera mask"
    with pytest.raises(ValueError, match="cannot merge"):
        a.merge(OccupancyMetric())


def test_metric_mask_policy():
    full = OccupancyMetric()
    with pytest.raises(ValueError, match="mask: this metric is over the full volume"):
        full.update(np.array([1]), np.array([1]), mask=np.array([True]))
    masked = OccupancyMetric(mask_name="camera")
    with pytest.raises(ValueError, match="mask: expected the 'camera' mask, got None"):
        masked.update(np.array([1]), np.array([1]))
