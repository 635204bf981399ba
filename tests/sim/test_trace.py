"""Tracing a checked planner's choices in one episode (renderworld.sim.closed_loop.trace)."""

import numpy as np
import pytest

from renderworld.planning.comfort import COMFORT_BOUNDS
from renderworld.sim.closed_loop import make_bundle_planners, run_closed_loop
from renderworld.sim.closed_loop.trace import trace_rows, trace_scene, write_trace
from tests.sim.test_closed_loop import _bundle, _world


def test_a_trace_replays_the_run_and_names_each_choice(tmp_path):
    world = _world(0)  # lead_brake
    checked, raw = make_bundle_planners(_bundle(tmp_path / "planner.pt"))
    run = run_closed_loop([world], [checked], progress=False)
    episode, results = trace_scene(world, checked)
    # The same episode as the run drove: the trace explains the run's scores.
    np.testing.assert_array_equal(episode.states, run.episodes[0].states)
    assert checked.results is None  # recording ends with the trace
    assert len(results) == len(episode.plan_ms) > 3
    rows = trace_rows(episode, results)
    assert [r["t"] for r in rows] == pytest.approx(0.5 * np.arange(len(rows)))
    for r, (_, res) in zip(rows, results):
        c = res.candidates
        assert r["kind"] == c.kind[c.best] and r["score"] == pytest.approx(c.score[c.best])
        assert r["plan_NC"] == c.NC[0] and r["plan_score"] == pytest.approx(c.score[0])
        assert r["accel_min"] <= r["accel_max"]
        assert r["yaw_rate_min"] <= r["yaw_rate_max"]
        # An uncomfortable learned plan names the quantity it broke, and by how much.
        if c.C[0] == 0:
            name, times = r["plan_comfort"].split()
            assert name in COMFORT_BOUNDS and float(times[:-1]) >= 1.0
        else:
            assert r["plan_comfort"] == ""
    assert rows[0]["speed"] == pytest.approx(episode.states[0, 3])
    # The driven heading rate of each plan's span (10 Hz states, central differences).
    rate = np.gradient(np.unwrap(episode.states[:, 2]), 0.1)
    t = np.asarray(episode.times) - episode.times[0]
    for k in (0, len(rows) // 2):
        span = (t >= rows[k]["t"] - 1e-9) & (t < rows[k]["t"] + 0.5 - 1e-9)
        assert rows[k]["yaw_rate_min"] == pytest.approx(rate[span].min())
        assert rows[k]["yaw_rate_max"] == pytest.approx(rate[span].max())
    path = write_trace(world, [raw, checked], tmp_path / "out")
    text = path.read_text()
    assert path.name == f"trace_{world.name}.md" and "world_model:" in text
    assert "world_model_raw" not in text  # the raw plan has no candidates to trace
    assert text.count("\n| ") == len(rows) + 1  # the header and one line per plan
    # A run from a nudged start is traced from that start.
    nudged = run_closed_loop([world], [checked], progress=False, nudge_m=0.05)
    assert nudged.episodes[0].states.tobytes() != run.episodes[0].states.tobytes()
    again, _ = trace_scene(world, checked, nudge_m=0.05)
    np.testing.assert_array_equal(again.states, nudged.episodes[0].states)
    with pytest.raises(ValueError, match="only a checked bundle planner"):
        trace_scene(world, raw)
    with pytest.raises(ValueError, match="trace=scene-.*: no checked planner"):
        write_trace(world, [raw], tmp_path / "out")


def test_the_drive_tool_refuses_a_trace_it_cannot_make_before_driving(tmp_path):
    from omegaconf import OmegaConf

    from tools.drive import drive

    cfg = OmegaConf.load("configs/drive.yaml")
    cfg.pop("hydra")
    cfg.pop("defaults")
    cfg.merge_with({"num_scenes": 1, "planners": ["cv"], "out": str(tmp_path), "progress": False,
                    "trace": "scene-6000"})  # fmt: skip
    with pytest.raises(ValueError, match="trace: .*pass planner=<bundle>"):
        drive(cfg)
    cfg.merge_with({"planner": str(_bundle(tmp_path / "planner.pt")), "trace": "scene-0"})
    with pytest.raises(ValueError, match="trace: no scene 'scene-0'"):
        drive(cfg)
    assert not (tmp_path / "closed_loop.md").exists()  # nothing was driven
