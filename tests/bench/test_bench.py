"""The accuracy-vs-time sweep: point expansion, fingerprints, resume, tables and Pareto plots.

The end-to-end test runs two real tokenizer points (3 steps each, tiny model) on the converted
tiny fixture through the same subprocess path as ``tools/bench.py``.
"""

from __future__ import annotations

import csv
import json
import math
import os
import threading
import time
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from data_converters import ConvertOptions, create_data
from renderworld.bench.knobs import KNOBS, format_value
from renderworld.bench.main import bench_points, resolve_jobs, write_outputs
from renderworld.bench.plots import pareto_front
from renderworld.bench.report import ranking_check, ranking_text, result_rows, stage_table
from renderworld.bench.run import run_sweep
from renderworld.bench.sweep import (
    RANKING,
    BenchPoint,
    expand_points,
    point_fingerprint,
)
from renderworld.training.checkpoint import load_checkpoint
from tests.training.conftest import compose_cfg


def _preset(**stages):
    return {"stages": stages}


TOK = {
    "experiment": "tokenizer_mini",
    "budget": {"max_steps": 10, "max_minutes": 1},
    "knobs": {"codebook_size": [64, 1024], "latent_size": [[50, 50]]},
}
WM = {"experiment": "world_model_mini", "budget": {"max_steps": 5}, "knobs": {"history": [3]}}


# ---------------------------------------------------------------------- Pareto front
def test_pareto_front_on_hand_made_points():
    # cost, value: (1, 10) (2, 20) (3, 15) dominated by (2, 20); (4, 30); (2, 5) dominated.
    costs = [1.0, 2.0, 3.0, 4.0, 2.0]
    values = [10.0, 20.0, 15.0, 30.0, 5.0]
    assert pareto_front(costs, values) == [0, 1, 3]


def test_pareto_front_keeps_ties_and_skips_nan():
    assert pareto_front([1.0, 1.0, 2.0], [5.0, 5.0, 5.0]) == [0, 1]
    assert pareto_front([1.0, float("nan"), 3.0], [1.0, 99.0, 2.0]) == [0, 2]
    assert pareto_front([], []) == []
    with pytest.raises(ValueError, match="costs, values: expected the same length, got 2 and 1"):
        pareto_front([1.0, 2.0], [1.0])


# ---------------------------------------------------------------------- expansion
def test_points_expand_default_first_then_each_knob_value_with_the_same_budget():
    pts = expand_points(_preset(tokenizer=TOK), common=["dataset.data_root=/d"])
    configs = [
        "tokenizer__default",
        "tokenizer__codebook_size-64",
        "tokenizer__codebook_size-1024",
        "tokenizer__latent_size-50x50",
    ]
    # Two seeds by default: every point once per seed, seed 0 first.
    assert [p.point_id for p in pts] == [f"{c}__s{s}" for s in (0, 1) for c in configs]
    budget = {"trainer.max_steps=10", "trainer.max_minutes=1.0", "trainer.val_every=0"}
    for p in pts:
        assert budget <= set(p.overrides)
        assert f"seed={p.seed}" in p.overrides and f"seed={p.seed}" not in p.eval_overrides
        assert p.overrides[0] == "dataset.data_root=/d"
        assert not budget & set(p.eval_overrides)  # the budget is for training only
    assert pts[0].overrides == pts[1].overrides[:-1]
    assert pts[1].overrides[-1] == "stage.model.codebook_size=64"
    assert pts[3].overrides[-1] == "stage.model.latent_shape=[50,50]"
    assert pts[3].eval_overrides[-1] == "stage.model.latent_shape=[50,50]"


def test_img2occ_accuracy_knobs_write_their_overrides():
    img = {
        "experiment": "img2occ_mini",
        "budget": {"max_steps": 10},
        "knobs": {"fine_semantics": [False], "feature_stride": [4], "backproject_weight": [0.0]},
        "seeds": [0],
    }
    pts = expand_points(_preset(img2occ=img))
    assert [p.overrides[-1] for p in pts[1:]] == [
        "stage.model.fine_semantics=false",
        "stage.model.feature_stride=4",
        "stage.model.backproject_weight=0.0",
    ]
    assert pts[1].point_id == "img2occ__fine_semantics-False__s0"
    with pytest.raises(TypeError, match="expected true or false for knob 'fine_semantics'"):
        expand_points(_preset(img2occ={**img, "knobs": {"fine_semantics": [1]}}))


def test_upstream_checkpoints_go_to_train_and_eval(tmp_path):
    ckpt = tmp_path / "tok.pt"
    ckpt.write_bytes(b"x")
    pts = expand_points(
        _preset(world_model=WM), upstream={"world_model": [f"stage.tokenizer_ckpt={ckpt}"]}
    )
    for p in pts:
        assert f"stage.tokenizer_ckpt={ckpt}" in p.overrides
        assert f"stage.tokenizer_ckpt={ckpt}" in p.eval_overrides
        assert p.upstream == (str(ckpt),)
    assert pts[1].overrides[-1] == "stage.history=3"
    assert "trainer.max_minutes='null'" not in pts[0].overrides
    assert "trainer.max_minutes=null" in pts[0].overrides


@pytest.mark.parametrize(
    "preset, err, match",
    [
        ({}, ValueError, "bench.stages: expected a non-empty mapping"),
        (_preset(nope={}), ValueError, r"bench.stages.nope: unknown stage 'nope'"),
        (
            _preset(tokenizer={**TOK, "seeds": [0, 0]}),
            ValueError,
            r"bench.stages.tokenizer.seeds: a seed is listed twice",
        ),
        (
            _preset(tokenizer={**TOK, "seeds": []}),
            ValueError,
            r"bench.stages.tokenizer.seeds: expected a non-empty list of int seeds",
        ),
        (
            _preset(
                tokenizer={
                    **TOK,
                    "ranking": {
                        "budget": {"max_steps": 9},
                        "points": ["default", "codebook_size-7", "codebook_size-64"],
                    },
                }
            ),
            ValueError,
            r"bench.stages.tokenizer.ranking.points: 'codebook_size-7' is not a point",
        ),
        (
            _preset(
                tokenizer={**TOK, "ranking": {"budget": {"max_steps": 9}, "points": ["default"]}}
            ),
            ValueError,
            r"bench.stages.tokenizer.ranking.points: expected at least 3 point names",
        ),
        (
            _preset(world_model={**WM, "knobs": {"scenario_library": [True]}}),
            ValueError,
            r"knobs.scenario_library: scenario_library=true needs the bench key",
        ),
        (
            _preset(planner={"windows": 0}),
            ValueError,
            r"bench.stages.planner.windows: expected an int >= 1",
        ),
        (
            _preset(planner={"budget": {"max_steps": 3}}),
            ValueError,
            r"bench.stages.planner.budget: unknown key",
        ),
        (
            _preset(tokenizer={**TOK, "knobs": {"history": [3]}}),
            ValueError,
            r"bench.stages.tokenizer.knobs.history: unknown knob for stage 'tokenizer'",
        ),
        (
            _preset(tokenizer={**TOK, "steps": 3}),
            ValueError,
            r"bench.stages.tokenizer.steps: unknown key",
        ),
        (
            _preset(tokenizer={**TOK, "budget": {"max_minutes": 2}}),
            ValueError,
            r"bench.stages.tokenizer.budget.max_steps: expected an int >= 1, got None",
        ),
        (
            _preset(tokenizer={**TOK, "budget": {"max_steps": 3, "max_minutes": -1}}),
            ValueError,
            r"bench.stages.tokenizer.budget.max_minutes: expected a number > 0",
        ),
        (
            _preset(tokenizer={**TOK, "experiment": None}),
            ValueError,
            r"bench.stages.tokenizer.experiment: expected an experiment name",
        ),
        (
            _preset(tokenizer={**TOK, "knobs": {"codebook_size": ["big"]}}),
            TypeError,
            r"bench.stages.tokenizer.knobs.codebook_size: expected an int for knob "
            r"'codebook_size', got 'big'",
        ),
        (
            _preset(tokenizer={**TOK, "knobs": {"latent_size": [[50]]}}),
            TypeError,
            r"knobs.latent_size: expected a pair of positive ints",
        ),
        (
            _preset(tokenizer={**TOK, "knobs": {"codebook_size": []}}),
            ValueError,
            r"bench.stages.tokenizer.knobs.codebook_size: expected a non-empty list",
        ),
        (
            _preset(tokenizer={**TOK, "knobs": {"codebook_size": [64, 64]}}),
            ValueError,
            r"the point 'tokenizer__codebook_size-64__s0' is listed twice",
        ),
    ],
)
def test_bad_presets_raise_naming_the_key(preset, err, match):
    with pytest.raises(err, match=match):
        expand_points(preset)


def test_every_knob_maps_to_a_key_of_the_stage_config():
    stage_keys = {
        "img2occ": "stage=img2occ",
        "tokenizer": "stage=tokenizer",
        "world_model": "stage=world_model",
    }
    for stage, knobs in KNOBS.items():
        if stage == "planner":  # options of the planner point, not of a training config
            from renderworld.bench.planner_point import planner_options

            assert set(knobs) <= set(planner_options([]))
            continue
        cfg = compose_cfg([stage_keys[stage]])
        for name, knob in knobs.items():
            if knob.key != "grid":
                assert OmegaConf.select(cfg, knob.key, default="MISSING") != "MISSING", name


# ---------------------------------------------------------------------- shipped presets
@pytest.fixture()
def fake_root(tmp_path):
    (tmp_path / "data" / "renderworld_infos").mkdir(parents=True)
    tok = tmp_path / "tok.pt"
    tok.write_bytes(b"x")
    wm = tmp_path / "wm.pt"
    wm.write_bytes(b"x")
    return tmp_path / "data", tok, wm


@pytest.mark.parametrize(
    "preset, ranking, count, ranked",
    [("quick", False, 16, 0), ("standard", False, 25, 0), ("standard", True, 43, 18),
     ("full", True, 91, 18)],
)  # fmt: skip
def test_shipped_presets_expand(fake_root, tmp_path, preset, ranking, count, ranked):
    data, tok, wm = fake_root
    cfg = compose_cfg(
        [f"bench={preset}", f"data_root={data}", f"tokenizer_ckpt={tok}",
         f"world_model_ckpt={wm}", f"bench.ranking={str(ranking).lower()}",
         f"scenario_library={tmp_path}", f"heldout_root={tmp_path / 'absent'}"],
        config_name="bench",
    )  # fmt: skip
    pts = bench_points(cfg)
    assert len(pts) == count and sum(bool(p.phase) for p in pts) == ranked
    assert {p.stage for p in pts} == {"img2occ", "tokenizer", "world_model", "planner"}
    assert str(cfg.out).endswith(f"outputs/bench/{preset}")
    wm_points = [p for p in pts if p.stage == "world_model"]
    # The main job's recipe: the scenario library (it exists here) in every world-model point,
    # off only in the knob's; no held-out scoring (its folder is absent).
    for p in wm_points:
        roots = [o for o in p.overrides if o.startswith("stage.extra_train_roots=")]
        assert roots[0] == f"stage.extra_train_roots=[{tmp_path}]"
        assert roots[-1] == ("stage.extra_train_roots=[]" if p.knob == "scenario_library"
                             else roots[0])  # fmt: skip
        assert not any(o.startswith("bench.heldout_root") for o in p.eval_overrides)
    assert {p.seed for p in wm_points} == {0, 1}


def test_bench_config_errors_name_the_key(fake_root, tmp_path):
    data, tok, wm = fake_root
    base = [f"data_root={data}", f"tokenizer_ckpt={tok}", f"world_model_ckpt={wm}"]
    cfg = compose_cfg([*base, "+bogus=1"], config_name="bench")
    with pytest.raises(ValueError, match="bogus: unknown bench key"):
        bench_points(cfg)
    cfg = compose_cfg([*base, f"data_root={tmp_path / 'nowhere'}"], config_name="bench")
    with pytest.raises(ValueError, match="data_root: .* has no renderworld_infos/"):
        bench_points(cfg)
    cfg = compose_cfg([*base, f"tokenizer_ckpt={tmp_path / 'no.pt'}"], config_name="bench")
    with pytest.raises(ValueError, match="tokenizer_ckpt: .* does not exist"):
        bench_points(cfg)
    cfg = compose_cfg([*base, f"world_model_ckpt={tmp_path / 'no.pt'}"], config_name="bench")
    with pytest.raises(ValueError, match="world_model_ckpt: .* does not exist"):
        bench_points(cfg)
    cfg = compose_cfg([*base, "bench.ranking=1"], config_name="bench")
    with pytest.raises(ValueError, match="bench.ranking: expected true or false"):
        bench_points(cfg)
    cfg = compose_cfg([*base, "+bench.extra=1"], config_name="bench")
    with pytest.raises(ValueError, match=r"bench.extra: unknown preset key"):
        bench_points(cfg)


def test_an_unknown_preset_is_refused_by_name():
    from hydra.errors import MissingConfigException

    with pytest.raises(MissingConfigException, match="bench/nope"):
        compose_cfg(["bench=nope"], config_name="bench")


# ---------------------------------------------------------------------- fingerprint, resume
def test_fingerprint_follows_overrides_budget_and_upstream_files(tmp_path):
    ckpt = tmp_path / "tok.pt"
    ckpt.write_bytes(b"x")
    p = BenchPoint("world_model", "default", None, "world_model_mini",
                   ("a=1", "trainer.max_steps=5"), ("a=1",), (str(ckpt),))  # fmt: skip
    fp = point_fingerprint(p, 5)
    assert fp == point_fingerprint(p, 5)
    assert fp != point_fingerprint(p, 6)
    q = BenchPoint(p.stage, p.knob, None, p.experiment, ("a=1", "trainer.max_steps=6"),
                   p.eval_overrides, p.upstream)  # fmt: skip
    assert fp != point_fingerprint(q, 5)
    st = ckpt.stat()
    os.utime(ckpt, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert fp != point_fingerprint(p, 5)


def _fake_runner(calls):
    def runner(point, point_dir, infer_frames, repo, timeout_s):
        calls.append(point.point_id)
        point_dir.mkdir(parents=True, exist_ok=True)
        return {
            "stage": point.stage, "knob": point.knob, "value": point.value,
            "knob_value": "", "steps": 10, "train_s": 1.0 + len(calls), "infer_ms": 2.0,
            "peak_rss_mib": 100.0, "metrics": {"val/miou": 0.5, "val/iou": 0.9},
        }  # fmt: skip

    return runner


def test_sweep_reuses_measured_points_and_reruns_changed_ones(tmp_path):
    calls: list[str] = []
    pts = expand_points(_preset(tokenizer=TOK))
    quiet = {"echo": lambda s: None, "runner": _fake_runner(calls)}
    first = run_sweep(pts, tmp_path, infer_frames=3, **quiet)
    assert calls == [p.point_id for p in pts]
    assert not any(r["reused"] for r in first)
    stored = json.loads(
        (tmp_path / "points" / "tokenizer__default__s0" / "result.json").read_text()
    )
    assert stored["fingerprint"] == point_fingerprint(pts[0], 3)

    calls.clear()
    again = run_sweep(pts, tmp_path, infer_frames=3, **quiet)
    assert calls == [] and all(r["reused"] for r in again)
    assert [r["train_s"] for r in again] == [r["train_s"] for r in first]

    # A changed budget re-measures every point; one changed knob value only that point.
    tok2 = {**TOK, "knobs": {"codebook_size": [64, 512], "latent_size": [[50, 50]]}}
    run_sweep(expand_points(_preset(tokenizer=tok2)), tmp_path, infer_frames=3, **quiet)
    assert calls == ["tokenizer__codebook_size-512__s0", "tokenizer__codebook_size-512__s1"]
    calls.clear()
    run_sweep(pts, tmp_path, infer_frames=3, overwrite=True, **quiet)
    assert calls == [p.point_id for p in pts]
    with pytest.raises(ValueError, match="infer_frames: expected an int >= 1, got 0"):
        run_sweep(pts, tmp_path, infer_frames=0, **quiet)


def test_sweep_with_two_jobs_runs_training_points_side_by_side_and_planner_points_alone(tmp_path):
    preset = _preset(tokenizer=TOK, planner={"knobs": {"forecast": [False]}})
    pts = expand_points(preset, upstream={"planner": ["tokenizer_ckpt=/t", "world_model_ckpt=/w"]})
    training = [p.point_id for p in pts if p.stage != "planner"]
    lock = threading.Lock()
    state = {"now": 0, "most": 0, "planner_beside": 0}
    calls: list[str] = []
    inner = _fake_runner(calls)

    def runner(point, point_dir, infer_frames, repo, timeout_s):
        with lock:
            state["now"] += 1
            state["most"] = max(state["most"], state["now"])
            if point.stage == "planner" and state["now"] > 1:
                state["planner_beside"] += 1
        time.sleep(0.05)  # long enough for a second job to start beside this one
        with lock:
            res = inner(point, point_dir, infer_frames, repo, timeout_s)
            state["now"] -= 1
        return res

    results = run_sweep(pts, tmp_path, infer_frames=3, runner=runner, echo=lambda s: None, jobs=2)
    assert [r["stage"] + r["knob"] for r in results] == [p.stage + p.knob for p in pts]
    assert [(r["seed"], r["reused"]) for r in results] == [(p.seed, False) for p in pts]
    assert state["most"] == 2 and state["planner_beside"] == 0
    assert calls[-2:] == [p.point_id for p in pts if p.stage == "planner"]
    assert {r["jobs"] for r in results if r["stage"] != "planner"} == {2}
    assert {r["jobs"] for r in results if r["stage"] == "planner"} == {1}
    stored = tmp_path / "points" / training[-1] / "result.json"
    assert json.loads(stored.read_text())["jobs"] == 2
    calls.clear()
    again = run_sweep(pts, tmp_path, infer_frames=3, runner=runner, echo=lambda s: None, jobs=2)
    assert calls == [] and all(r["reused"] for r in again)
    with pytest.raises(ValueError, match="jobs: expected an int >= 1, got 0"):
        run_sweep(pts, tmp_path, infer_frames=3, runner=runner, jobs=0)


def test_jobs_default_to_the_cores_up_to_two_and_bad_values_name_the_key(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert resolve_jobs(None) == 2 and resolve_jobs(3) == 3
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    assert resolve_jobs(None) == 1
    for bad in (0, "2", True, 1.5):
        with pytest.raises(ValueError, match="jobs: expected an int >= 1 or null"):
            resolve_jobs(bad)


def test_sweep_with_two_jobs_starts_nothing_after_a_failure_and_keeps_what_ran(tmp_path):
    pts = expand_points(_preset(tokenizer=TOK))
    calls: list[str] = []
    inner = _fake_runner(calls)

    def runner(point, point_dir, infer_frames, repo, timeout_s):
        if point.point_id == pts[1].point_id:
            raise RuntimeError(f"bench point {point.point_id} failed (exit 1)")
        time.sleep(0.1)
        return inner(point, point_dir, infer_frames, repo, timeout_s)

    with pytest.raises(RuntimeError, match=f"bench point {pts[1].point_id} failed"):
        run_sweep(pts, tmp_path, infer_frames=3, runner=runner, echo=lambda s: None, jobs=2)
    # The point running beside the failed one finished and kept its result; none started after.
    assert calls == [pts[0].point_id]
    assert (tmp_path / "points" / pts[0].point_id / "result.json").is_file()
    assert not (tmp_path / "points" / pts[2].point_id).exists()


# ---------------------------------------------------------------------- writers
def _synthetic(stage="tokenizer"):
    def res(knob, value, miou, train_s, infer_ms, seed=0, phase="", steps=100):
        return {
            "stage": stage, "knob": knob, "value": value, "seed": seed, "phase": phase,
            "knob_value": format_value(value) if value else "",
            "knob_values": {"codebook_size": "256"}, "steps": steps, "max_steps": steps,
            "max_minutes": 1.5, "train_s": train_s, "train_wall_s": train_s + 3, "eval_s": 2.0,
            "infer_ms": infer_ms, "infer_frames": 5, "peak_rss_mib": 600.0 + seed, "params": 1000,
            "grid": "coarse", "experiment": "tokenizer_mini", "fingerprint": "f",
            "metrics": {"val/miou": miou, "val/iou": 0.9},
        }  # fmt: skip

    return [
        res("codebook_size", 64, 0.30, 20.0, 8.0),
        res("default", None, 0.40, 40.0, 10.0),
        res("codebook_size", 1024, 0.35, 80.0, 30.0),
        res("latent_size", [50, 50], float("nan"), 10.0, 5.0),
        # second seeds: the default moves by 0.02, K = 64 by 0.04, K = 1024 by 0.10
        res("codebook_size", 64, 0.34, 22.0, 8.0, seed=1),
        res("default", None, 0.42, 42.0, 10.0, seed=1),
        res("codebook_size", 1024, 0.45, 82.0, 30.0, seed=1),
        res("latent_size", [50, 50], float("nan"), 10.0, 5.0, seed=1),
    ]


def test_table_shows_seed_means_and_spread_and_calls_small_deltas_no_difference():
    rows = result_rows(_synthetic())
    table = stage_table(rows, "tokenizer")
    lines = [line for line in table.splitlines() if line.startswith("| ")]
    assert len(lines) == 5  # header + one row per point, seeds merged
    rule = next(line for line in table.splitlines() if line.startswith("|---"))
    assert {line.count("|") for line in [*lines, rule]} == {lines[0].count("|")}  # GFM: same width
    assert "Measured 1 point(s) at a time" in table
    two = stage_table([{**r, "jobs": 2} for r in rows], "tokenizer")
    assert "Measured 2 point(s) at a time" in two
    # default: mean 41.00, ± half the range 1.00; train 41 s
    assert lines[1].startswith("| **default** (codebook_size=256) | 41.00 | 1.00 | +0.00 |")
    # K = 64: mean 32.00, Δ -9.00 beyond both ranges (4.00 and 2.00)
    assert (
        "| codebook_size=64 | 32.00 | 2.00 | -9.00 | 90.00 | 100 | 21 | 0.51× | 8.0 | 0.80× |"
        in (lines[2])
    )
    # K = 1024: mean 40.00, Δ -1.00 within its own range 10.00: no difference
    assert "| codebook_size=1024 | 40.00 | 5.00 | -1.00 (no difference) |" in lines[3]
    assert "| 81 | 1.98× | 30.0 | 3.00× | 601 |" in lines[3]  # peak RSS: the larger seed's
    assert lines[4].startswith("| latent_size=50x50 | – | – | – |")  # NaN metric shown
    assert "100 steps, capped at 1.5 min" in table and "seeds per point: 2" in table
    assert "Ranking not claimed" not in table
    unclaimed = [{**r, "claimed": False} for r in rows]
    assert "**Ranking not claimed**" in stage_table(unclaimed, "tokenizer")


def test_ranking_check_compares_orders_and_ignores_ties_within_the_spread():
    budget = _synthetic()[:3] + _synthetic()[4:7]  # default 41, K=64 32, K=1024 40 (tie w/ def.)
    # The default's composed knob values name the step count where steps is a knob (the world
    # model's): they differ between the two budgets and must still pair.
    full = [
        {**r, "phase": RANKING, "max_steps": 700, "metrics": {"val/miou": m, "val/iou": 0.9},
         "knob_values": {"codebook_size": "256", "steps": "700"}}
        for r, m in zip(budget, (0.55, 0.50, 0.60, 0.55, 0.50, 0.60), strict=True)
    ]  # fmt: skip
    # rows K=64, default, K=1024 per seed; at 700 steps: K=1024 60 > K=64 55 > default 50
    rows = result_rows(budget + full)
    chk = ranking_check(rows, "tokenizer")
    assert chk["budget_order"] == [
        "default 41.00",
        "codebook_size=1024 40.00",
        "codebook_size=64 32.00",
    ]
    assert chk["full_order"] == [
        "codebook_size=1024 60.00",
        "codebook_size=64 55.00",
        "default 50.00",
    ]
    # default > K=64 at the budget (beyond the spread) is reversed at 700 steps: contradiction;
    # default vs K=1024 was a tie at the budget: not one.
    assert chk["contradictions"] == [("codebook_size=64", "default")] and not chk["holds"]
    # The ranking points get their own table: means and spreads at 700 steps, Δ vs that default.
    table = stage_table(rows, "tokenizer", RANKING)
    assert "**tokenizer** ranking points (the main job's step count)" in table
    assert "700 steps" in table and "| codebook_size=1024 | 60.00 | 0.00 | +10.00 |" in table
    assert "| 41.00 |" not in table  # no budget point in it
    # K=1024's seeds span 10 points: within it of both others at the budget.
    assert chk["ties"] == [
        ("codebook_size=64", "codebook_size=1024"),
        ("default", "codebook_size=1024"),
    ]
    text = ranking_text(rows, "tokenizer")
    assert "does not hold" in text
    assert (
        "No difference at the budget (within the seeds' spread): codebook_size=64 vs "
        "codebook_size=1024; default vs codebook_size=1024." in text
    )
    same = [
        {**r, "metrics": {"val/miou": m, "val/iou": 0.9}}
        for r, m in zip(full, (0.50, 0.60, 0.58, 0.50, 0.60, 0.58), strict=True)
    ]  # the budget's order: default > K=1024 > K=64
    chk = ranking_check(result_rows(budget + same), "tokenizer")
    assert chk["holds"] and chk["full_steps"] == 700
    assert ranking_check(result_rows(budget), "tokenizer") is None


def test_outputs_csv_markdown_and_png(tmp_path):
    results = _synthetic() + _synthetic("world_model")[:2]
    for r in results[8:]:
        r["metrics"] = {"val/model/miou_avg": 0.1, "val/model/l2_at_horizon_3s": 2.5}
    paths = write_outputs(results, tmp_path, "title", notes=["a note"])
    rows = list(csv.DictReader(paths["csv"].open()))
    assert len(rows) == 10 and [r["seed"] for r in rows[:8]] == ["0"] * 4 + ["1"] * 4
    assert rows[0]["metric_name"] == "val/miou" and float(rows[0]["metric"]) == 0.30
    assert rows[8]["metric2_name"] == "val/model/l2_at_horizon_3s"
    assert math.isnan(float(rows[3]["metric"]))
    md = paths["md"].read_text()
    assert md.startswith("# title") and "**tokenizer**" in md and "**world_model**" in md
    assert "| 2.50 |" in md  # L2 in metres, not as a percentage
    assert md.rstrip().endswith("a note")
    for stage in ("tokenizer", "world_model"):
        png = paths[f"pareto_{stage}"]
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000


# ---------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def converted(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_infos")
    create_data(tiny_dataset, "v1.0-mini", out=out, options=ConvertOptions(progress=False))
    return tiny_dataset, out


def test_sweep_end_to_end_on_two_tiny_tokenizer_points(converted, tmp_path):
    root, infos = converted
    tiny = [
        f"stage.infos_dir={infos}", "trainer.batch_size=2", "stage.model.latent_channels=8",
        "stage.model.base_channels=8", "stage.model.codebook_size=32",
    ]  # fmt: skip
    preset = _preset(
        tokenizer={
            "experiment": "tokenizer_mini",
            "budget": {"max_steps": 3, "max_minutes": 1},
            "overrides": tiny,
            "knobs": {"codebook_size": [16]},
            "seeds": [1],
        }
    )
    pts = expand_points(preset, common=[f"dataset.data_root={root}"])
    log: list[str] = []
    results = run_sweep(pts, tmp_path, infer_frames=2, echo=log.append)
    assert [r["steps"] for r in results] == [3, 3]
    for r in results:
        assert 0.0 <= r["metrics"]["val/miou"] <= 1.0
        assert r["train_s"] > 0 and r["infer_ms"] > 0 and r["peak_rss_mib"] > 50
        assert r["torch_threads"] == 1 and r["seed"] == 1
        assert 0 < r["train_cpu_s"] < r["point_cpu_s"]
    assert results[0]["knob_values"]["codebook_size"] == "32"
    assert results[1]["knob_value"] == "16"
    # The knob really reached the trained model: its checkpoint's config has it.
    point = tmp_path / "points" / "tokenizer__codebook_size-16__s1"
    stored = OmegaConf.create(
        load_checkpoint(point / "train" / "checkpoints" / "last.pt")["config"]
    )
    assert stored.stage.model.codebook_size == 16 and stored.seed == 1  # so did the seed
    assert (point / "eval" / "eval_metrics.json").is_file()
    again = run_sweep(pts, tmp_path, infer_frames=2, echo=log.append)
    assert all(r["reused"] for r in again)
    paths = write_outputs(again, tmp_path)
    assert Path(paths["pareto_tokenizer"]).is_file()
    assert any("reused" in line for line in log)


def test_planner_rows_table_in_metres_and_a_latency_only_plot(tmp_path):
    def res(knob, value, l2, ms):
        return {
            "stage": "planner", "knob": knob, "value": value, "seed": 0, "phase": "",
            "knob_value": "" if value is None else str(value).lower(),
            "knob_values": {"forecast": "true"}, "steps": 0, "max_steps": 0, "max_minutes": None,
            "train_s": 0.0, "infer_ms": ms, "peak_rss_mib": 500.0, "params": 10,
            "grid": "mini 50x50x4", "metrics": {"val/l2_3s": l2, "val/forecast_equal": 1.0},
        }  # fmt: skip

    results = [res("default", None, 1.83, 120.0), res("forecast", False, 1.83, 40.0),
               res("grid", "occ3d", float("nan"), 900.0)]  # fmt: skip
    paths = write_outputs(results, tmp_path)
    md = paths["md"].read_text()
    assert "no training (latency of the main job's planner)" in md
    assert "| **default** (forecast=true) | 1.83 | – | +0.00 | 100.00 |" in md  # L2 in metres
    assert "| forecast=false | 1.83 | – | +0.00 |" in md and "| 40.0 | 0.33× |" in md
    assert paths["pareto_planner"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------- time estimate
def test_estimate_charges_steps_the_library_and_halves_the_wall_time_with_two_jobs(tmp_path):
    from renderworld.bench.estimate import estimate, estimate_text, point_seconds

    wm = {"experiment": "world_model_mini", "budget": {"max_steps": 400}, "knobs": {}}
    plain = expand_points(_preset(world_model=wm))[0]
    longer = expand_points(_preset(world_model={**wm, "budget": {"max_steps": 800}}))[0]
    library = expand_points(
        _preset(world_model=wm), upstream={"world_model": ["stage.extra_train_roots=[/lib]"]}
    )[0]
    assert point_seconds(plain) < point_seconds(library) < point_seconds(longer) + 200
    assert point_seconds(longer) > 1.5 * point_seconds(plain)  # the steps dominate at 400

    pts = expand_points(_preset(tokenizer=TOK))
    left = estimate(pts, tmp_path, 3)["left_s"]
    assert left == pytest.approx(sum(point_seconds(p) for p in pts))
    one, two = estimate_text(pts, tmp_path, 3, 1), estimate_text(pts, tmp_path, 3, 2)
    assert "of wall time left" not in one
    assert f"2 points at a time: about {left / 2 / 60:.0f} min of wall time left" in two
    # A measured point counts its recorded wall time and is not left to run.
    run_sweep(pts[:1], tmp_path, infer_frames=3, runner=_fake_runner([]), echo=lambda s: None)
    est = estimate(pts, tmp_path, 3)
    assert est["done"] == 1 and est["left_s"] == pytest.approx(left - point_seconds(pts[0]))
    # Planner points run alone: they count in full, and only while they are still to run.
    pp = expand_points(
        _preset(planner={"knobs": {"forecast": [False]}}),
        upstream={"planner": ["tokenizer_ckpt=/t", "world_model_ckpt=/w"]},
    )
    both = pts + pp
    est = estimate(both, tmp_path, 3)
    assert est["left_alone_s"] == pytest.approx(sum(point_seconds(p) for p in pp))
    wall = (est["left_s"] - est["left_alone_s"]) / 2 + est["left_alone_s"]
    assert f"about {wall / 60:.0f} min of wall time left" in estimate_text(both, tmp_path, 3, 2)
    run_sweep(pp, tmp_path, infer_frames=3, runner=_fake_runner([]), echo=lambda s: None)
    assert estimate(both, tmp_path, 3)["left_alone_s"] == 0.0
