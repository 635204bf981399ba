"""benchmarks/checked_choice.py's summary: the choice per kind and the ground truth's refusals."""

from benchmarks.checked_choice import summary

_OK = {"NC": 1.0, "DAC": 1.0, "EP": 1.0, "TTC": 1.0, "C": 1.0, "score": 1.0}


def _record(kind="plan", gt=None, worst="yaw_accel", **plan):
    rec = {"command": "gt", "token": "t", "kind": kind, "offset": 0.0, "horizon_step": 5,
           "l2_raw": 1.0, "l2_checked": 2.0, "l2_plan_cand": 1.5, "plan_held": False,
           "plan": {**_OK, **plan}, "plan_choice": 1.0, "best": _OK,
           "best_choice": 1.0}  # fmt: skip
    if gt is not None:
        rec["gt"], rec["gt_comfort_worst"] = {**_OK, **gt}, worst
    return rec


def test_the_ground_truth_refusals_are_counted_by_failed_sub_score():
    records = [
        _record(gt={}),  # the check accepts what the car did
        _record(gt={"C": 0.0}),
        _record(kind="steady_idm", C=0.0, gt={"C": 0.0, "TTC": 0.0}, worst="lon_jerk"),
        _record(gt={"EP": 0.5}),
        _record(),  # a window whose future is cut short: no ground-truth row
    ]
    text = summary(records)
    assert "The learned plan lost in 1 windows" in text
    assert "refused in 3 of 4 windows" in text
    assert "| C (yaw_accel) | 1 |" in text
    assert "| TTC, C (lon_jerk) | 1 |" in text
    assert "| EP | 1 |" in text


def test_without_ground_truth_rows_the_table_is_left_out():
    assert "ground-truth future" not in summary([_record(), _record(kind="brake", DAC=0.0)])


def test_collisions_at_3_s_are_counted_by_the_candidate_driven():
    records = [_record(), _record(kind="idm"), _record(), _record(kind="brake")]
    for r, (checked, raw) in zip(records, [(True, True), (True, False), (False, True),
                                           (False, False)]):  # fmt: skip
        r["hit_checked"], r["hit_raw"] = checked, raw
    text = summary(records)
    assert "meets a ground-truth box at 3 s in 2 windows (the raw plan in 2)" in text
    assert "| plan, no offset, the raw plan too | 1 |" in text
    assert "| idm | 1 |" in text


def test_behaviours_and_the_scenes_adding_most_l2_are_tabled():
    records = [_record(), _record(), _record(), _record()]
    for r, scene, beh, raw, checked in zip(records, ["a", "a", "b", "c"],
                                           ["cut_in", "cut_in", "lead_brake", ""],
                                           [1.0, 1.0, 0.5, 2.0], [5.0, 3.0, 0.5, 2.5]):  # fmt: skip
        r.update(scene=scene, behaviour=beh, l2_raw=raw, l2_checked=checked)
        r["hit_raw"] = beh == "cut_in"
    text = summary(records)
    assert "| cut_in | 2 | 1.00 | 4.00 | 6.0 | 2 / 0 |" in text
    assert "| (none) | 1 | 2.00 | 2.50 | 0.5 | 0 / 0 |" in text
    rows = [line for line in text.splitlines() if line.startswith(("| a |", "| b |", "| c |"))]
    assert [row[:5] for row in rows] == ["| a |", "| c |", "| b |"]  # most L2 added first
    assert "| behaviour |" not in summary([_record()])  # records without scenes: no table
