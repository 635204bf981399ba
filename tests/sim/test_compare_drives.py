"""Paired comparison of two closed-loop runs (closed_loop.compare, tools/compare_drives.py)."""

from __future__ import annotations

import json

import pandas as pd
import pytest
from omegaconf import OmegaConf

from renderworld.sim.closed_loop.compare import (
    average_runs,
    compare_runs,
    comparison_markdown,
    load_run,
)
from tools.compare_drives import compare


def write_run(path, rows):
    """A closed_loop.csv of (scene, behaviour, planner, PDMS, at_fault) rows."""
    path.mkdir(parents=True, exist_ok=True)
    recs = []
    for scene, beh, planner, pdms, fault in rows:
        recs.append({"scene": scene, "behaviour": beh, "planner": planner, "PDMS": pdms,
                     "EP": pdms, "TTC": 1.0, "C": 1.0, "NC": 0.0 if fault else 1.0, "DAC": 1.0,
                     "at_fault_collision": fault, "off_road": False})  # fmt: skip
    pd.DataFrame(recs).to_csv(path / "closed_loop.csv", index=False)
    return path


@pytest.fixture
def runs(tmp_path):
    wm, lb = "world_model", "lead_brake"
    a = write_run(tmp_path / "a", [
        ("s1", "cut_in", wm, 0.8, False), ("s2", "cut_in", wm, 0.0, True),
        ("s3", lb, wm, 0.9, False), ("s4", lb, wm, 0.5, False),
        ("s1", "cut_in", "rule_based", 1.0, False),
    ])  # fmt: skip
    b = write_run(tmp_path / "b", [
        ("s1", "cut_in", wm, 0.8, False), ("s2", "cut_in", wm, 0.7, False),
        ("s3", lb, wm, 0.6, False), ("s5", lb, wm, 1.0, False),
    ])  # fmt: skip
    return a, b


def test_scenes_are_paired_and_counted_per_behaviour(runs):
    a, b = runs
    cmp = compare_runs(load_run(a, "world_model", "a"), load_run(b, "world_model", "b"), top=2)
    assert cmp["scenes"] == 3 and cmp["only_a"] == ["s4"] and cmp["only_b"] == ["s5"]
    o = cmp["overall"]
    assert o["PDMS_a"] == pytest.approx((0.8 + 0.0 + 0.9) / 3)
    assert o["PDMS_b"] == pytest.approx((0.8 + 0.7 + 0.6) / 3)
    assert (o["up"], o["down"]) == (1, 1)  # s2 up, s3 down, s1 the same
    # The standard error of the paired differences (0, +0.7, -0.3) over 3 scenes.
    assert o["PDMS_se"] == pytest.approx(pd.Series([0.0, 0.7, -0.3]).std() / 3**0.5)
    assert cmp["behaviours"]["lead_brake"]["PDMS_se"] != cmp["behaviours"]["lead_brake"]["PDMS_se"]
    assert (o["at_fault_collision_a"], o["at_fault_collision_b"]) == (1, 0)
    assert cmp["behaviours"]["cut_in"]["n"] == 2 and cmp["behaviours"]["lead_brake"]["n"] == 1
    assert [m[0] for m in cmp["moved"]] == ["s2", "s3"]  # largest change first, unchanged left out
    md = comparison_markdown(cmp)
    assert "| all | 3 |" in md and "s2 (cut_in): 0.000 → 0.700" in md and "s4" in md
    assert f"| +0.133 ± {o['PDMS_se']:.3f} |" in md
    assert "| -0.300 | 0 / 1 |" in md  # lead_brake, one scene: no standard error


def test_the_tool_prints_and_writes_the_tables_and_compares_two_planners(runs, tmp_path, capsys):
    a, b = runs
    out = tmp_path / "cmp.md"
    cfg = OmegaConf.create({"a": str(a), "b": str(a / "closed_loop.csv"), "planner": "world_model",
                            "planner_b": "rule_based", "top": 5, "out": str(out)})  # fmt: skip
    res = compare(cfg)
    assert res["comparison"]["scenes"] == 1  # rule_based drove s1 only
    assert out.read_text().startswith("| scenes |") and "rule_based" in capsys.readouterr().out


def test_bad_input_names_the_run(runs, tmp_path):
    a, b = runs
    with pytest.raises(FileNotFoundError, match="b: no closed_loop.csv"):
        load_run(tmp_path / "nowhere", "world_model", "b")
    with pytest.raises(ValueError, match=r"no rows of planner 'camera'.*rule_based"):
        load_run(a, "camera", "a")
    other = write_run(tmp_path / "c", [("z9", "cut_in", "world_model", 1.0, False)])
    with pytest.raises(ValueError, match="share no scene"):
        compare_runs(load_run(a, "world_model"), load_run(other, "world_model"))
    clash = write_run(tmp_path / "d", [("s1", "ped_crossing", "world_model", 1.0, False)])
    with pytest.raises(ValueError, match="different behaviours"):
        compare_runs(load_run(a, "world_model"), load_run(clash, "world_model"))
    (tmp_path / "e").mkdir()
    pd.DataFrame({"scene": ["s1"], "planner": ["world_model"]}).to_csv(
        tmp_path / "e" / "closed_loop.csv", index=False
    )
    with pytest.raises(ValueError, match="a: .* lacks columns"):
        load_run(tmp_path / "e", "world_model", "a")


def test_runs_of_other_worlds_are_refused_though_their_scene_names_match(runs):
    a, b = runs
    for path, seed in ((a, 1002), (b, 7)):  # the dev interactions against the interaction split
        settings = {"preset": "interactions", "seed": seed, "scenes": ["s1"]}
        (path / "closed_loop.json").write_text(json.dumps({"settings": settings}))
    with pytest.raises(ValueError, match="different worlds.*1002.*7"):
        compare_runs(load_run(a, "world_model", "a"), load_run(b, "world_model", "b"))
    # The same preset and seed pair as before; a run without its json is not checked.
    (b / "closed_loop.json").write_text(json.dumps({"settings": {"preset": "interactions",
                                                                 "seed": 1002}}))  # fmt: skip
    assert compare_runs(load_run(a, "world_model"), load_run(b, "world_model"))["scenes"] == 3
    (b / "closed_loop.json").unlink()
    assert load_run(b, "world_model").attrs["worlds"] is None
    assert compare_runs(load_run(a, "world_model"), load_run(b, "world_model"))["scenes"] == 3


def test_a_side_of_several_runs_is_compared_by_each_scenes_mean_and_lists_its_runs(
    runs, tmp_path, capsys
):
    a, b = runs
    wm, lb = "world_model", "lead_brake"
    a2 = write_run(tmp_path / "a2", [  # another training of a: s1 and s3 drove otherwise
        ("s1", "cut_in", wm, 0.6, False), ("s2", "cut_in", wm, 0.0, True),
        ("s3", lb, wm, 0.3, True), ("s4", lb, wm, 0.5, False),
    ])  # fmt: skip
    side = average_runs([load_run(a, wm, "a"), load_run(a2, wm, "a")], "a")
    assert side.loc["s1", "PDMS"] == pytest.approx(0.7) and side.loc["s3", "PDMS"] == 0.6
    assert side.loc["s3", "at_fault_collision"] == 0.5 and side.attrs["runs"] == 2
    cmp = compare_runs(side, load_run(b, wm, "b"))
    o = cmp["overall"]
    assert o["PDMS_a"] == pytest.approx((0.7 + 0.0 + 0.6) / 3)
    assert o["at_fault_collision_a"] == 1.5  # per run: s2 in both, s3 in one of the two
    assert "| 1.50 → 0 |" in comparison_markdown(cmp)
    # The tool: each run's own mean over the paired scenes, and how far apart they lie.
    cfg = OmegaConf.create({"a": [str(a), str(a2)], "b": str(b), "planner": wm,
                            "planner_b": None, "top": 3, "out": None})  # fmt: skip
    md = compare(cfg)["markdown"]
    m1, m2 = (0.8 + 0.0 + 0.9) / 3, (0.6 + 0.0 + 0.3) / 3
    assert f"a: 2 runs, PDMS {m1:.3f} / {m2:.3f} (at fault 1 / 2)" in md
    assert f"lie up to {m1 - m2:.3f} apart" in md and "b: 1 run, PDMS" in md
    assert str(a2) in capsys.readouterr().out
    # One run a side: no such line, the tables as before.
    one = compare(OmegaConf.create({**cfg, "a": str(a)}))["markdown"]
    assert "runs of one side" not in one and one.startswith("| scenes |")


def test_runs_of_one_side_must_drive_the_same_scenes(runs, tmp_path):
    a, b = runs
    wm = "world_model"
    short = write_run(tmp_path / "short", [("s1", "cut_in", wm, 1.0, False)])
    with pytest.raises(ValueError, match=r"a: run 2 and run 1 drove other scenes"):
        average_runs([load_run(a, wm), load_run(short, wm)], "a")
    clash = write_run(tmp_path / "clash", [
        ("s1", "ped_crossing", wm, 1.0, False), ("s2", "cut_in", wm, 1.0, False),
        ("s3", "lead_brake", wm, 1.0, False), ("s4", "lead_brake", wm, 1.0, False),
    ])  # fmt: skip
    with pytest.raises(ValueError, match="b: run 2 gives a scene another behaviour"):
        average_runs([load_run(a, wm), load_run(clash, wm)], "b")
    with pytest.raises(ValueError, match="a: no run given"):
        average_runs([], "a")
    # The same scene names from worlds of another seed are other scenes.
    other = write_run(tmp_path / "other", [
        ("s1", "cut_in", wm, 1.0, False), ("s2", "cut_in", wm, 1.0, False),
        ("s3", "lead_brake", wm, 1.0, False), ("s4", "lead_brake", wm, 1.0, False),
    ])  # fmt: skip
    for path, seed in ((a, 1002), (other, 7)):
        settings = {"preset": "interactions", "seed": seed}
        (path / "closed_loop.json").write_text(json.dumps({"settings": settings}))
    with pytest.raises(ValueError, match="a: run 2 drove other worlds than run 1"):
        average_runs([load_run(a, wm), load_run(other, wm)], "a")
