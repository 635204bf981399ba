import math

import numpy as np
import pytest

from renderworld.constants import FREE_ID, GridSpec
from renderworld.metrics import PlanningMetric, l2_errors

SMALL = GridSpec("small", (-10.0, -10.0, 0.0), (10.0, 10.0, 2.0), (40, 40, 2))


def straight(speed=2.0, s=6):
    return np.column_stack([speed * np.arange(1, s + 1), np.zeros(s)])


def no_agents(s=6):
    return np.zeros((s, 0, 5))


def test_l2_both_conventions_hand_case():
    gt = straight()
    pred = gt.copy()
    pred[:, 0] += [0, 1, 0, 2, 0, 3]
    m = PlanningMetric()
    m.update(pred, gt)
    r = m.compute()
    assert r["l2_at_horizon@1s"] == pytest.approx(1.0)
    assert r["l2_at_horizon@2s"] == pytest.approx(2.0)
    assert r["l2_at_horizon@3s"] == pytest.approx(3.0)
    assert r["l2_at_horizon_avg"] == pytest.approx(2.0)
    assert r["l2_mean_to_horizon@1s"] == pytest.approx(0.5)
    assert r["l2_mean_to_horizon@2s"] == pytest.approx(0.75)
    assert r["l2_mean_to_horizon@3s"] == pytest.approx(1.0)
    assert r["l2_mean_to_horizon_avg"] == pytest.approx(0.75)
    assert "collision_boxes_at_horizon@1s" not in r  # a source never given is absent, not 0
    assert "UniAD" in r["protocol"] and "ST-P3/VAD" in m.format_table()


def test_perfect_plan_and_l2_errors():
    gt = straight()
    m = PlanningMetric()
    m.update(gt[None].repeat(3, 0), gt[None].repeat(3, 0), agent_boxes=[no_agents()] * 3)
    r = m.compute()
    assert r["l2_at_horizon_avg"] == 0.0 and r["collision_boxes_at_horizon_avg"] == 0.0
    np.testing.assert_allclose(l2_errors(np.zeros((2, 2)), np.array([[3.0, 4.0], [0, 0]])), [5, 0])
    with pytest.raises(ValueError, match="pred/gt: expected finite"):
        l2_errors(np.full((6, 2), np.nan), gt)


def test_masked_steps_are_excluded_and_counted():
    gt = straight()
    pred = gt.copy()
    pred[4:, 1] += 10.0  # huge errors only where the scene already ended
    valid = np.array([True] * 4 + [False] * 2)
    m = PlanningMetric()
    m.update(pred, gt, valid=valid)
    r = m.compute()
    assert r["masked_steps"] == 2
    assert r["l2_mean_to_horizon@3s"] == 0.0
    assert math.isnan(r["l2_at_horizon@3s"])  # no valid sample at 3 s: NaN, not 0


def test_collision_rates_and_gt_collision_skipping():
    gt = straight()  # waypoints (2,0) (4,0) ... (12,0)
    boxes = np.full((6, 2, 5), np.nan)
    valid_rows = np.zeros((6, 2), dtype=bool)
    boxes[1, 0] = [4.0, 3.0, 4.0, 2.0, 0.0]  # step 2: beside GT, hit by a plan swerving left
    valid_rows[1, 0] = True
    boxes[3, 0] = [8.0, 0.0, 4.0, 2.0, 0.0]  # step 4: on the GT path itself (GT collides)
    valid_rows[3, 0] = True
    pred = gt.copy()
    pred[1, 1] = 2.5  # swerve at step 2 only
    m = PlanningMetric()
    m.update(pred[None], gt[None], agent_boxes=[boxes], agent_valid=[valid_rows])
    r = m.compute()
    assert r["collision_boxes_gt_skipped"] == 1
    assert r["collision_boxes_at_horizon@1s"] == 1.0  # the step-2 swerve collides
    assert math.isnan(r["collision_boxes_at_horizon@2s"])  # step 4 skipped: GT collides there
    assert r["collision_boxes_at_horizon@3s"] == 0.0
    assert r["collision_boxes_mean_to_horizon@1s"] == pytest.approx(1 / 2)
    assert r["collision_boxes_mean_to_horizon@2s"] == pytest.approx(1 / 3)  # step 4 excluded
    assert r["collision_boxes_mean_to_horizon@3s"] == pytest.approx(1 / 5)
    # The counts behind the rates: hits / evaluated waypoints.
    assert (
        r["collision_boxes_hits_at_horizon@1s"],
        r["collision_boxes_evaluated_at_horizon@1s"],
    ) == (1, 1)
    assert r["collision_boxes_evaluated_at_horizon@2s"] == 0
    assert (r["collision_boxes_hits_mean_to_horizon@3s"],
            r["collision_boxes_evaluated_mean_to_horizon@3s"]) == (1, 5)  # fmt: skip


def test_occupancy_source_and_outside_grid():
    gt = np.column_stack([np.arange(1, 7) * 1.0, np.zeros(6)])  # 1 m per step
    occ = np.full((6, *SMALL.shape), FREE_ID, dtype=np.uint8)
    occ[0, 20, 30, 0] = 4  # a car at (0.25, 5.25) at step 1 only (current-frame occupancy)
    pred = gt.copy()
    pred[:, 1] = 5.0  # plan drives 5 m to the left: through the car at step 1
    pred[5, 0] = 40.0  # last waypoint outside the 20 m occupancy grid
    m = PlanningMetric(occupancy_grid=SMALL)
    m.update(pred, gt, occupancy=occ)
    r = m.compute()
    assert r["collision_occupancy_outside_grid"] == 1
    assert r["collision_occupancy_gt_skipped"] == 0
    assert r["collision_occupancy_mean_to_horizon@1s"] == pytest.approx(1 / 2)
    assert math.isnan(r["collision_occupancy_at_horizon@3s"])
    assert "collision_boxes_at_horizon@1s" not in r


def test_merge_and_validation():
    gt = straight()
    a, b, whole = PlanningMetric(), PlanningMetric(), PlanningMetric()
    for i, off in enumerate((0.5, 1.5, 2.0)):
        pred = gt + off
        whole.update(pred, gt, agent_boxes=no_agents())
        (a if i else b).update(pred, gt, agent_boxes=no_agents())
    ra, rw = a.merge(b).compute(), whole.compute()
    for k, v in rw.items():
        if isinstance(v, float):
            assert ra[k] == pytest.approx(v, nan_ok=True), k
        else:
            assert ra[k] == v, k
    with pytest.raises(ValueError, match=r"pred: expected \[B, 6, 2\]"):
        PlanningMetric().update(gt[:5], gt[:5])
    with pytest.raises(ValueError, match="valid: expected bool"):
        PlanningMetric().update(gt, gt, valid=np.ones(6))
    with pytest.raises(ValueError, match="boxes: expected"):
        PlanningMetric().update(gt, gt, agent_boxes=np.zeros((5, 1, 5)))
