import math

import pytest
import torch

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer import (
    ConfusionMeter,
    confusion_matrix,
    metrics_from_confusion,
    reconstruction_metrics,
)


def test_hand_made_confusion_and_ious():
    # 8 voxels: truth car car road road free free free free
    car, road = 4, 11
    target = torch.tensor([car, car, road, road, FREE_ID, FREE_ID, FREE_ID, FREE_ID])
    pred = torch.tensor([car, road, road, road, FREE_ID, FREE_ID, car, 2])
    conf = confusion_matrix(pred, target)
    assert conf.shape == (NUM_OCC3D_CLASSES, NUM_OCC3D_CLASSES) and int(conf.sum()) == 8
    assert conf[car, car] == 1 and conf[car, road] == 1 and conf[FREE_ID, 2] == 1
    m = metrics_from_confusion(conf)
    # car: TP 1, FP 1 (free->car), FN 1 -> 1/3; road: TP 2, FP 1 -> 2/3; bicycle (2): 0/1 -> 0.
    assert m["per_class_iou"][car] == pytest.approx(1 / 3)
    assert m["per_class_iou"][road] == pytest.approx(2 / 3)
    assert m["per_class_iou"][2] == 0.0
    assert math.isnan(m["per_class_iou"][3])  # absent and never predicted: excluded
    assert m["miou"] == pytest.approx((1 / 3 + 2 / 3 + 0.0) / 3)
    # geometry: occupied truth {0,1,2,3}, occupied pred {0,1,2,3,6,7}: IoU 4/6
    assert m["iou"] == pytest.approx(4 / 6)
    assert m["num_voxels"] == 8


def test_accumulation_equals_one_big_batch_and_mask():
    g = torch.Generator().manual_seed(0)
    a = torch.randint(0, NUM_OCC3D_CLASSES, (3, 4, 4, 2), generator=g)
    b = torch.randint(0, NUM_OCC3D_CLASSES, (3, 4, 4, 2), generator=g)
    meter = ConfusionMeter()
    for i in range(3):
        meter.update(a[i], b[i])
    assert meter.compute() == reconstruction_metrics(a, b)
    mask = torch.zeros_like(a, dtype=torch.bool)
    mask[0] = True
    assert reconstruction_metrics(a, b, mask) == reconstruction_metrics(a[0], b[0])


def test_all_free_volume_gives_nan_miou_not_an_error():
    free = torch.full((2, 3), FREE_ID)
    m = reconstruction_metrics(free, free)
    assert math.isnan(m["miou"]) and math.isnan(m["iou"])
    assert m["per_class_iou"][FREE_ID] == 1.0


def test_bad_inputs():
    t = torch.zeros(4, dtype=torch.int64)
    with pytest.raises(ValueError, match="pred: expected the shape"):
        confusion_matrix(t[:3], t)
    with pytest.raises(ValueError, match="pred: expected labels in \\[0, 17\\]"):
        confusion_matrix(t + 18, t)
    with pytest.raises(ValueError, match="target: expected integer class labels"):
        confusion_matrix(t, t.float())
    with pytest.raises(ValueError, match="mask: expected bool"):
        confusion_matrix(t, t, torch.ones(4))
