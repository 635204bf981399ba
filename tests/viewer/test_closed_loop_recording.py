"""The Rerun recording of closed-loop episodes (renderworld.viewer.closed_loop)."""

import pytest

rr = pytest.importorskip("rerun", reason="rerun-sdk is not installed (pip install '.[viz]')")
from rerun.chunk import RrdReader  # noqa: E402

from renderworld.sim import build_world  # noqa: E402
from renderworld.sim.closed_loop import make_planner, run_episode  # noqa: E402
from renderworld.viewer.closed_loop import write_episode_recording  # noqa: E402
from tools.make_fixtures import config_from_preset  # noqa: E402


def test_recording_has_every_planner_ego_path_agents_and_the_collision(tmp_path):
    cfg = config_from_preset("interactions")
    world = build_world(cfg.scene_names[0], cfg.scenes[0], cfg.keyframes, cfg.seed, 0)
    eps = [run_episode(world, make_planner(n)) for n in ("log_replay", "cv")]
    assert eps[1].end == "collision"
    out = write_episode_recording(world, eps, tmp_path / "ep.rrd")
    times: dict = {}
    for chunk in RrdReader(out).stream():
        if chunk.is_static:
            times.setdefault(chunk.entity_path, set())
            continue
        rb = chunk.to_record_batch()
        times.setdefault(chunk.entity_path, set()).update(rb.column("sim_time").to_pylist())
    for p in ("log_replay", "cv"):
        assert f"/world/{p}/ego" in times and f"/world/{p}/path" in times
    assert "/world/logged_path" in times and "/world/agents" in times
    assert "/world/cv/collision" in times and "/world/log_replay/collision" not in times
    # 10 Hz from the start (2 s) to the scene end (10.5 s) for the agents.
    assert len(times["/world/agents"]) == len(eps[0].times) == 86
    with pytest.raises(ValueError, match="expected scene"):
        other = build_world(cfg.scene_names[1], cfg.scenes[1], cfg.keyframes, cfg.seed, 1)
        write_episode_recording(other, eps, tmp_path / "x.rrd")
