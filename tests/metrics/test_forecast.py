import math

import numpy as np
import pytest

from renderworld.constants import FREE_ID
from renderworld.metrics import ForecastMetric, horizon_steps
from renderworld.metrics.forecast import movers_miou


def test_horizon_steps():
    assert horizon_steps() == (2, 4, 6)
    with pytest.raises(ValueError, match="horizons_s"):
        horizon_steps((0.7,))


def frames(s=6):
    gt = np.full((s, 4, 4, 2), FREE_ID, dtype=np.uint8)
    gt[:, 1, 1, 0] = 4
    gt[:, 2, 2, 0] = 11
    return gt


def test_values_are_taken_at_steps_2_4_6_not_averaged():
    gt = frames()
    pred = np.full_like(gt, FREE_ID)  # all wrong ...
    pred[1] = gt[1]  # ... except step 2 (1 s)
    pred[3, 1, 1, 0] = 4  # step 4 (2 s): car right, road missed
    pred[0] = gt[0]  # step 1 is perfect but reported nowhere
    m = ForecastMetric()
    m.update(pred, gt)
    r = m.compute()
    assert r["miou@1s"] == 1.0 and r["iou@1s"] == 1.0
    assert r["miou@2s"] == pytest.approx(0.5) and r["iou@2s"] == pytest.approx(0.5)
    assert r["miou@3s"] == 0.0 and r["iou@3s"] == 0.0
    assert r["miou_avg"] == pytest.approx(0.5)
    assert r["miou_per_step"][0] == 1.0 and len(r["miou_per_step"]) == 6
    assert "1s=step 2" in r["protocol"] and "full volume" in m.format_table()


def test_validity_excludes_and_counts_frames_past_scene_end():
    gt = frames()[None].repeat(2, axis=0)
    pred = gt.copy()
    pred[1, 5] = FREE_ID  # wrong at 3 s, but that frame lies past the scene end
    valid = np.ones((2, 6), dtype=bool)
    valid[1, 5] = False
    m = ForecastMetric()
    m.update(pred, gt, valid=valid)
    r = m.compute()
    assert r["miou@3s"] == 1.0 and r["skipped_frames"] == 1
    # Nothing valid at a step: NaN, not 0.
    m2 = ForecastMetric()
    m2.update(pred, gt, valid=np.zeros((2, 6), dtype=bool))
    assert math.isnan(m2.compute()["miou@1s"]) and m2.compute()["skipped_frames"] == 12


def test_masked_forecast_and_validation():
    gt = frames()
    pred = np.full_like(gt, FREE_ID)
    mask = np.zeros(gt.shape, dtype=bool)
    mask[:, 3, 3] = True  # only a free voxel is visible: nothing occupied in view
    m = ForecastMetric(mask_name="camera")
    m.update(pred, gt, mask=mask)
    assert math.isnan(m.compute()["miou@1s"]) and "camera" in m.compute()["region"]
    with pytest.raises(ValueError, match="pred: expected"):
        ForecastMetric().update(pred[:5], gt[:5])
    with pytest.raises(ValueError, match="valid: expected bool"):
        ForecastMetric().update(pred, gt, valid=np.ones(6, dtype=int))


def test_movers_miou_is_the_mean_over_the_movable_classes_of_the_same_confusion():
    gt = np.full((6, 4, 4, 2), FREE_ID, dtype=np.uint8)
    gt[:, 0, 0, 0] = gt[:, 0, 1, 0] = 4  # car, 2 voxels
    gt[:, 3, 3, 0] = 7  # pedestrian
    gt[:, 2, :, 0] = 11  # road (not a mover)
    gt[:, 1, 3, 0] = 1  # barrier (an object, not a mover)
    pred = gt.copy()
    pred[:, 0, 1, 0] = FREE_ID  # car IoU 1/2
    pred[:, 3, 3, 0] = 8  # pedestrian missed (IoU 0), a traffic cone instead
    pred[:, 1, 3, 0] = FREE_ID  # barrier missed: the mIoU sees it, the movers' mIoU does not
    m = ForecastMetric()
    m.update(pred, gt)
    r = m.compute()
    assert r["movers_miou@1s"] == pytest.approx((0.5 + 0.0) / 2)  # car, pedestrian; others absent
    assert r["miou@1s"] == pytest.approx((0.5 + 0 + 1 + 0 + 0) / 5)  # + road, barrier, cone
    assert r["movers_miou_per_step"] == [pytest.approx(0.25)] * 6
    assert movers_miou(m.per_step[0].confusion) == pytest.approx(0.25)
    assert math.isnan(movers_miou(np.zeros((18, 18), dtype=np.int64)))
