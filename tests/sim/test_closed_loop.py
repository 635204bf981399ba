"""Closed-loop driving (renderworld.sim.closed_loop, tools/drive.py) on the interaction preset."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from renderworld.constants import GRIDS, KEYFRAME_DT
from renderworld.data.downsample import downsample_occupancy
from renderworld.planning import load_planner, register_tokenizer, save_planner_bundle
from renderworld.sim import build_world, build_worlds
from renderworld.sim.closed_loop import (
    BundlePlanner,
    ClosedLoopRun,
    EgoState,
    KinematicLimits,
    OccupancyRenderer,
    SceneBoxes,
    make_bundle_planners,
    make_planner,
    route_command,
    run_closed_loop,
    run_episode,
    score_episode,
    self_check,
    track_plan,
)
from renderworld.sim.closed_loop.boxes import EGO_HALF, first_contact
from renderworld.sim.closed_loop.observe import pose_matrix_2d
from renderworld.sim.layout import EGO_CENTRE_OFFSET
from renderworld.sim.occupancy import SemanticVoxeliser
from renderworld.sim.scene import INTERACTIONS
from renderworld.world import WorldModelConfig
from renderworld.world.ego import command_from_trajectory
from renderworld.world.pose import PoseWarpWorldModel
from tests.world.fake_tokenizer import PatchTokenizer, PatchTokenizerConfig
from tools.make_fixtures import config_from_preset

register_tokenizer("test_patch", PatchTokenizer)
COARSE = GRIDS["coarse"]


@pytest.fixture(scope="module")
def interactions():
    """The 16 scenes of the interaction preset (the held-out split's worlds)."""
    return build_worlds(config_from_preset("interactions"))


def _world(i):
    cfg = config_from_preset("interactions")
    return build_world(cfg.scene_names[i], cfg.scenes[i], cfg.keyframes, cfg.seed, i)


def _bundle(path, grid=COARSE, seed=0):
    torch.manual_seed(seed)
    tok = PatchTokenizer(PatchTokenizerConfig(tuple(grid.shape), patch=2, num_codebooks=2))
    cfg = WorldModelConfig(
        codebook_sizes=tok.codebook_sizes, token_grid=tok.token_grid, embed_dim=16,
        num_heads=2, num_scales=2, layers_per_scale=(1, 1),
    )  # fmt: skip
    wm = PoseWarpWorldModel(cfg, anchors="ctr_cv")
    with torch.no_grad():  # a pose head that is not its anchor
        for p in wm.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return save_planner_bundle(path, tok, wm, grid=grid)


class _Fixed:
    """A planner returning one fixed answer (or recording what it sees)."""

    privileged = False
    grid = None

    def __init__(self, answer, name="fixed", grid=None):
        self.answer, self.name, self.grid, self.seen = answer, name, grid, []

    def reset(self, world):
        self.seen = []

    def plan(self, obs):
        self.seen.append(obs)
        return self.answer(obs) if callable(self.answer) else self.answer


def test_self_check_reads_ep_to_a_tolerance_and_names_the_scene():
    def row(ep, **kw):
        r = {
            "planner": "log_replay",
            "scene": "scene-1",
            "behaviour": "turn_left",
            "end": "scene_end",
            "collision": False,
            "collided_with": "",
            "DAC": 1.0,
            "EP": ep,
        }
        return {**r, **kw}  # fmt: skip

    run = ClosedLoopRun(rows=[row(1.0), row(1.0 - 1e-6, scene="scene-2")])
    assert self_check(run) == []  # millimetres short of the log over a stop mid-turn
    run.rows += [row(0.999, scene="scene-3"), row(1.0, scene="scene-4", DAC=0.0)]
    bad = self_check(run)
    assert len(bad) == 2 and bad[0].startswith("scene-3") and bad[1].startswith("scene-4")
    assert self_check(run, planner="rule_based") == []


def test_reference_planners_meet_the_bars(interactions):
    run = run_closed_loop(
        interactions, [make_planner(n) for n in ("log_replay", "cv", "rule_based")], progress=False
    )
    assert self_check(run) == []  # log replay: no collision, DAC 1, EP 1 on every scene
    lr = run.summary["log_replay"]
    assert (lr["NC"], lr["DAC"], lr["EP"], lr["collisions"]) == (1.0, 1.0, 1.0, 0)
    n = len(interactions)
    assert run.summary["cv"]["at_fault_collisions"] >= 0.4 * n  # the scenes are built for it
    assert run.summary["rule_based"]["at_fault_collisions"] <= 0.1 * n
    assert set(run.by_behaviour["cv"]) == {
        "lead_brake", "cut_in", "ped_crossing", "turn_oncoming", "overtake_parked"
    }  # fmt: skip
    assert run.planners["rule_based"]["privileged"] and not run.planners["cv"]["privileged"]


def test_same_seed_and_bundle_give_bit_identical_scores(tmp_path):
    path = _bundle(tmp_path / "planner.pt")
    runs, states = [], []
    for _ in range(2):
        worlds = [_world(0), _world(12)]
        run = run_closed_loop(worlds, [make_planner(str(path))], progress=False)
        scores = [{k: v for k, v in r.items() if not k.endswith("_ms")} for r in run.rows]
        runs.append(json.dumps(scores, sort_keys=True))  # everything but the timings
        states.append(np.concatenate([e.states for e in run.episodes]))
        assert run.timing["world_model"]["voxelise_ms"] > 0
    assert runs[0] == runs[1]
    assert states[0].tobytes() == states[1].tobytes()  # every 10 Hz state, bit for bit


def test_bundle_on_another_grid_is_refused(tmp_path):
    path = _bundle(tmp_path / "planner.pt")
    with pytest.raises(ValueError, match=r"bundle's grid coarse \(50, 50, 4\).*run's grid half"):
        make_planner(str(path), grid=GRIDS["half"])
    with pytest.raises(ValueError, match="expected one of .* or a planner bundle path"):
        make_planner("constant_speed")
    assert BundlePlanner(load_planner(path), grid=COARSE).grid == COARSE


def test_scene_too_short_for_the_history_names_it():
    cfg = config_from_preset("tiny", keyframes=5)
    world = build_worlds(cfg)[0]
    with pytest.raises(ValueError, match=rf"scene {world.name}: 5 keyframes, expected at least 6"):
        run_episode(world, make_planner("cv"))


@pytest.mark.parametrize(
    ("answer", "reason"),
    [
        (np.full((6, 2), np.nan), "NaN or inf"),
        (np.array([[80.0, 0.0]] * 6), "impossible step of 80 m"),
        (np.zeros((6, 3)), r"expected shape \[S >= 1, 2\], got \[6, 3\]"),
    ],
)
def test_bad_plans_end_the_episode_as_a_counted_failure(answer, reason):
    world = _world(0)
    ep = run_episode(world, _Fixed(answer))
    assert ep.end == "planner_error" and len(ep.plan_ms) == 1
    assert pytest.approx(ep.times[-1]) == 2.0  # nothing driven
    import re

    assert re.search(reason, ep.reason), ep.reason
    row = score_episode(world, ep)
    assert row["failed"] and row["PDMS"] == 0.0


def test_occupancy_is_rendered_at_the_actual_pose_on_the_planner_grid():
    world = _world(0)
    stand = _Fixed(np.zeros((6, 2)), grid=COARSE)  # brakes to a stop: leaves the log behind
    ep = run_episode(world, stand, KinematicLimits(max_decel=8.0))
    obs = stand.seen[-1]
    assert len(obs.occupancy) == 5 and obs.occupancy[-1].shape == tuple(COARSE.shape)
    actual = pose_matrix_2d(*obs.pose)
    fine = SemanticVoxeliser().semantics(world, obs.t, actual)
    np.testing.assert_array_equal(obs.occupancy[-1], downsample_occupancy(fine, (4, 4, 4)))
    logged = OccupancyRenderer(COARSE).render(
        world,
        obs.t,
        pose_matrix_2d(
            *world.ego.trajectory.pose(obs.t)[0], float(world.ego.trajectory.pose(obs.t)[1])
        ),
    )
    assert not np.array_equal(obs.occupancy[-1], logged)
    # The history is the actual one: the ego stood still for the last steps.
    assert np.abs(obs.displacements[-1]).max() < 1e-6 and ep.states[-1, 3] == 0.0


def test_kinematic_model_follows_a_feasible_plan_and_saturates_an_impossible_one():
    start = EgoState(0.0, 0.0, 0.0, 10.0)
    plan = np.stack([5.0 * np.arange(1, 7), np.zeros(6)], 1)
    states, sat = track_plan(start, plan, KinematicLimits(), 5)
    assert sat == 0 and states[-1].x == pytest.approx(5.0)
    assert states[-1].speed == pytest.approx(10.0)
    lim = KinematicLimits(max_accel=4.0, max_yaw_rate=1.0)
    jump = np.stack([40.0 * np.arange(1, 7), 20.0 * np.arange(1, 7)], 1)
    states, sat = track_plan(start, jump, lim, 5)
    v = np.array([start.speed] + [s.speed for s in states])
    yaw = np.array([start.yaw] + [s.yaw for s in states])
    assert sat == 5
    assert np.diff(v).max() <= lim.max_accel * 0.1 + 1e-9
    assert np.abs(np.diff(yaw)).max() <= lim.max_yaw_rate * 0.1 + 1e-9


def test_route_command_matches_the_dataset_rule_along_the_log():
    world = _world(9)  # turn_oncoming: straight, then left, then straight
    traj = world.ego.trajectory
    got, want = [], []
    for k in range(4, 21):
        t = k * KEYFRAME_DT
        (x, y), yaw = traj.pose(t)
        got.append(route_command(world, x, y, float(yaw)))
        fut_t = t + KEYFRAME_DT * np.arange(1, 7)
        c, s = np.cos(yaw), np.sin(yaw)
        d = traj.pose(fut_t)[0] - np.array([x, y])
        local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)
        want.append(command_from_trajectory(local, fut_t <= world.duration + 1e-9))
    moving = [traj.speed(k * KEYFRAME_DT) > 0.5 for k in range(4, 21)]
    assert [g for g, m in zip(got, moving) if m] == [w for w, m in zip(want, moving) if m]
    assert "left" in got and "straight" in got


def test_rear_contact_is_not_at_fault_and_a_front_one_is():
    world = _world(0)  # lead_brake: the lead car ahead in the ego lane
    boxes = SceneBoxes(world)
    i = boxes.keys.index("scn_lead")
    t = 1.0
    c, yaw = boxes.at(t)
    rear = c[i, 0] - boxes.half[i, 0]
    x_hit = rear - EGO_CENTRE_OFFSET - EGO_HALF[0] + 0.1  # ego front 0.1 m into the lead's rear
    hit = first_contact(boxes, t, x_hit, c[i, 1], 0.0)
    assert hit is not None and hit.key == "scn_lead" and hit.at_fault
    front = c[i, 0] + boxes.half[i, 0]
    x_ahead = front + EGO_HALF[0] - EGO_CENTRE_OFFSET - 0.1  # lead's front into the ego's rear
    hit = first_contact(boxes, t, x_ahead, c[i, 1], 0.0)
    assert hit is not None and hit.key == "scn_lead" and not hit.at_fault
    assert first_contact(boxes, t, x_hit - 1.0, c[i, 1], 0.0) is None


def test_drive_tool_writes_tables_and_pictures(tmp_path):
    from tools.drive import drive

    cfg = OmegaConf.load("configs/drive.yaml")
    cfg.merge_with({"num_scenes": 2, "planners": ["log_replay", "cv"], "out": str(tmp_path),
                    "progress": False})  # fmt: skip
    cfg.pop("hydra")
    cfg.pop("defaults")
    result = drive(cfg)
    assert result["self_check"] == []
    data = json.loads((tmp_path / "closed_loop.json").read_text())
    assert set(data["summary"]) == {"log_replay", "cv"} and len(data["rows"]) == 4
    assert data["settings"]["nudge_m"] == 0.0  # the start a run was driven from, recorded
    md = (tmp_path / "closed_loop.md").read_text()
    assert "| cv |" in md and "PDMS" in md and "voxelise ms/plan" in md
    assert (tmp_path / "closed_loop.csv").read_text().count("\n") == 5
    assert (tmp_path / "figures" / "closed_loop_lead_brake.png").stat().st_size > 10_000


def test_progress_counts_only_along_the_route():
    from renderworld.sim.agents import Path
    from renderworld.sim.closed_loop.scores import route_progress

    path = Path(np.array([[0.0, 0.0], [100.0, 0.0]]))
    along = np.stack([np.linspace(0, 30, 31), np.zeros(31)], 1)
    assert route_progress(path, along) == pytest.approx(30.0)
    off = along.copy()
    off[11:, 1] = 6.0  # leaves the route after 10 m: nothing more counts
    assert route_progress(path, off) == pytest.approx(10.0)


def test_true_movers_row_checks_against_the_scenes_real_future(tmp_path):
    from renderworld.sim.closed_loop.oracle import MATCH_M, true_mover_forecaster
    from renderworld.world.tracks import MoverTrack

    world = _world(0)  # lead_brake: the lead car slows down
    boxes = SceneBoxes(world)
    t, pose = 2.0, (5.0, -1.0, 0.3)
    lead = int(np.flatnonzero(boxes.moving)[0])
    c, s = np.cos(pose[2]), np.sin(pose[2])
    rot = np.array([[c, s], [-s, c]])  # scene -> ego
    centre = rot @ (boxes.at(t)[0][lead] - pose[:2])
    cells = np.zeros(COARSE.shape[:2], bool)

    def track(xy):
        xy = np.asarray(xy, np.float64)
        return MoverTrack(1, cells, xy, np.zeros(1), xy[None], np.zeros(2), False)

    far = centre + (MATCH_M + 5.0, 0.0)  # no object near it: the fallback's forecast
    fallback = lambda tr, *a: np.full((len(tr), 7, 2), 9.0)  # noqa: E731
    disp = true_mover_forecaster(boxes, t, pose, fallback)(
        [track(centre + 0.5), track(far)], None, None, COARSE, 6, KEYFRAME_DT
    )
    truth = np.stack([rot @ (boxes.at(t + 0.5 * k)[0][lead] - boxes.at(t)[0][lead])
                      for k in range(7)])  # fmt: skip
    np.testing.assert_allclose(disp[0], truth, atol=1e-9)
    assert np.linalg.norm(truth[-1]) > 1.0  # it moves
    assert (disp[1] == 9.0).all()

    rows = make_bundle_planners(_bundle(tmp_path / "planner.pt"), true_movers=True)
    assert [p.name for p in rows] == ["world_model", "world_model_raw", "world_model_true_movers"]
    run = run_closed_loop([world], rows, progress=False)
    assert run.planners["world_model_true_movers"]["privileged"]
    assert not run.planners["world_model"]["privileged"]
    with pytest.raises(ValueError, match="true_movers needs check=True"):
        BundlePlanner(rows[0].planner, check=False, true_movers=True)


def test_drive_tool_selects_planner_dev_scenes_and_checker_knobs():
    from tools.drive import check_config, select_worlds

    worlds = build_worlds(config_from_preset("scenarios", num_scenes=24))
    dev = select_worlds(worlds, "interactions", 5)
    assert len(dev) == 5 and all(w.spec.behaviour in INTERACTIONS for w in dev)
    first = [w.name for w in worlds if w.spec.behaviour in INTERACTIONS][:5]
    assert [w.name for w in dev] == first  # preset order
    cut_ins = sum(w.spec.behaviour == "cut_in" for w in worlds)
    assert len(select_worlds(worlds, ["cut_in"])) == cut_ins > 0
    with pytest.raises(ValueError, match="behaviours: \\['flying'\\]"):
        select_worlds(worlds, ["cut_in", "flying"])
    two = [worlds[3].name, worlds[1].name]
    assert [w.name for w in select_worlds(worlds, scenes=two)] == [worlds[1].name, worlds[3].name]
    assert [w.name for w in select_worlds(worlds, scenes=worlds[2].name)] == [worlds[2].name]
    with pytest.raises(ValueError, match="scenes: \\['scene-0'\\] not in this preset"):
        select_worlds(worlds, scenes=[worlds[0].name, "scene-0"])
    cfg = check_config(OmegaConf.create({"headway": 1.0, "offsets_m": [0.0, 1.0]}))
    assert cfg.headway == 1.0 and cfg.offsets_m == (0.0, 1.0) and cfg.steady_path
    with pytest.raises(ValueError, match="check.head_way: CheckConfig has no such knob"):
        check_config({"head_way": 1.0})


def test_drive_command_line_sets_checker_knobs():
    """``tools/drive.py check={KNOB: VALUE}``, as the docs give it, reaches the checked plan."""
    from hydra import compose, initialize_config_dir

    from tools.drive import check_config

    configs = str(Path(__file__).resolve().parents[2] / "configs")
    with initialize_config_dir(config_dir=configs, version_base="1.3"):
        cfg = compose("drive", overrides=["check={headway: 1.0, steady_path: false}"])
        plain = compose("drive")
    knobs = check_config(cfg.check)
    assert knobs.headway == 1.0 and not knobs.steady_path and knobs.a_max == 1.5
    assert not plain.check  # no knobs: the bundle's own checked plan


def test_a_nudged_start_moves_the_ego_along_its_heading_and_nothing_else():
    world = _world(0)
    cv = make_planner("cv")
    base = run_episode(world, cv)
    assert run_episode(world, cv, nudge_m=0.0).states.tobytes() == base.states.tobytes()
    seen = _Fixed(lambda obs: cv.plan(obs))
    ep = run_episode(world, seen, nudge_m=0.25)
    (x, y), yaw = world.ego.trajectory.pose(2.0)
    np.testing.assert_allclose(ep.states[0, :2], [x + 0.25 * np.cos(yaw), y + 0.25 * np.sin(yaw)])
    assert ep.states[0, 2:].tobytes() == base.states[0, 2:].tobytes()  # heading, speed: the log's
    logged = _Fixed(lambda obs: cv.plan(obs))
    run_episode(world, logged)
    # The first plan sees the last history step 0.25 m longer, the earlier steps as logged.
    first, ref = seen.seen[0].displacements, logged.seen[0].displacements
    np.testing.assert_allclose(np.hypot(*first[-1]), np.hypot(*ref[-1]) + 0.25, atol=1e-6)
    np.testing.assert_allclose(first[:-1], ref[:-1], atol=1e-9)
    with pytest.raises(ValueError, match="nudge_m: expected a finite distance"):
        run_episode(world, cv, nudge_m=float("nan"))
