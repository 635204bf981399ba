"""The closed-loop scores' NAVSIM rules, on hand-made worlds and episodes.

The world: a straight two-way road along +x (two 3.5 m lanes per direction, 2.5 m parking
strips, kerbs at y = +-9.5 m); the logged ego drives lane 0 (y = -1.75 m) at 8 m/s from the
origin. Optionally a crossing road at x = 60 m makes a junction (x in [50.5, 69.5] m).
"""

import numpy as np
import pytest

from renderworld.sim.agents import Path, Trajectory
from renderworld.sim.closed_loop import (
    COMFORT_BOUNDS,
    Contact,
    Episode,
    LaneMap,
    SceneBoxes,
    add_best_progress,
    comfort_signals,
    comfort_violations,
    comfort_windows,
    contacts_at,
    is_agent,
    make_planner,
    run_closed_loop,
    run_episode,
    score_episode,
    write_outputs,
)
from renderworld.sim.closed_loop.contacts import EGO_HALF, contact_at_fault
from renderworld.sim.layout import EGO_CENTRE_OFFSET, EgoPlan, World, motion_times
from renderworld.sim.objects import make_object
from renderworld.sim.roads import GroundRaster, Junction, Road, RoadNetwork
from renderworld.sim.scene import SceneSpec

V_LOG = 8.0  # m/s, the logged ego
LANE0 = -1.75  # y of the ego lane's centre
FRONT = EGO_CENTRE_OFFSET + EGO_HALF[0]  # rear axle -> front bumper, m
DT = 0.1
CAR = (1.9, 4.6, 1.6)  # width, length, height


def _world(objects=(), junction=False, duration=6.0) -> World:
    road = Road(np.array([[-100.0, 0.0], [200.0, 0.0]]))
    roads, junctions = [road], []
    if junction:
        roads.append(Road(np.array([[60.0, -100.0], [60.0, 100.0]])))
        junctions.append(Junction((60.0, 0.0), ("+x", "-x", "+y", "-y"), road.half_width,
                                  road.half_width))  # fmt: skip
    network = RoadNetwork(roads, junctions)
    raster = GroundRaster(network, (-40.0, -30.0, 120.0, 30.0), cell=0.2)
    times = motion_times(duration)
    path = Path(np.array([[-50.0, LANE0], [150.0, LANE0]]))
    ego = EgoPlan(path, Trajectory.along(path, 50.0 + V_LOG * times, times))
    return World("hand-0", SceneSpec(), network, raster, ego, list(objects), duration)


def _obj(key, cat, xy_of_t, yaw=0.0, size=CAR, moving=True):
    """An object whose centre is ``xy_of_t(t)`` (scene frame) at every motion time."""
    times = motion_times(12.0)
    xy = np.array([xy_of_t(t) for t in times], dtype=np.float64)
    traj = Trajectory(times, xy, np.full(len(times), yaw))
    return make_object(key, cat, size, traj, np.random.default_rng(0), moving=moving)


def _still(key, cat, x, y, size=CAR, moving=False):
    return _obj(key, cat, lambda t: (x, y), size=size, moving=moving)


class _Cruise:
    """Straight ahead at a constant speed (ego frame waypoints 0.5 s apart)."""

    name, grid, privileged = "cruise", None, False

    def __init__(self, speed=V_LOG, name="cruise"):
        self.speed, self.name = speed, name

    def reset(self, world):
        pass

    def plan(self, obs):
        return np.stack([self.speed * 0.5 * np.arange(1, 7), np.zeros(6)], 1)


def _episode(states, t0=2.0, contacts=()):
    states = np.asarray(states, dtype=np.float64)
    ep = Episode("hand-0", "cruise", "hand", t0 + DT * np.arange(len(states)), states, "scene_end")
    ep.not_at_fault_contacts = list(contacts)
    return ep


def _drive(x, y, v, n=2):
    """n 10 Hz states along +x at speed v (the first is the start), rear axle at (x, y) last."""
    xs = x - v * DT * np.arange(n)[::-1]
    return np.stack([xs, np.full(n, y), np.zeros(n), np.full(n, v)], 1)


# ------------------------------------------------------------------ at fault (NAVSIM's rules)


def test_lanes_under_the_ego_box():
    lanes = LaneMap(_world(junction=True).network)
    pts = [[0, -1.0], [0, -4.0], [0, -8.0], [0, 1.0], [0, 5.0], [0, 12.0], [60.0, 3.0]]
    assert lanes.lane_ids(np.array(pts, float)) == [
        (0, 0), (0, 1), None, (0, -1), (0, -2), None, ("junction",)
    ]  # fmt: skip
    box = np.array([[2.0, -6.5], [-2.0, -6.5], [-2.0, -8.4], [2.0, -8.4]])  # lane 1 + parking
    assert not lanes.straddles(box)  # corners in no lane do not count (NAVSIM)
    assert lanes.straddles(box + [0.0, 4.0])  # lanes 0 and 1
    with pytest.raises(ValueError, match="pts: expected shape"):
        lanes.lane_ids(np.zeros((3, 3)))


def test_a_stopped_ego_is_not_at_fault_and_a_moving_one_is():
    t = 1.0
    world = _world([_obj("car", "vehicle.car", lambda s: (30.0 + 5.0 * s, LANE0))])
    boxes = SceneBoxes(world)
    x = 35.0 - 2.3 - FRONT + 0.1  # the ego's front bumper 0.1 m into the car's back
    for speed, kind, fault in [(0.0, "stopped_ego", False), (0.05, "stopped_ego", False),
                               (0.06, "front", True)]:  # fmt: skip
        (hit,) = contacts_at(boxes, t, x, LANE0, 0.0, speed)
        assert (hit.key, hit.kind, hit.at_fault) == ("car", kind, fault), speed


def test_a_rear_contact_is_not_at_fault():
    t = 1.0
    world = _world([_obj("car", "vehicle.car", lambda s: (30.0 + 9.0 * s, LANE0))])
    boxes = SceneBoxes(world)
    x = 39.0 + 2.3 + (EGO_HALF[0] - EGO_CENTRE_OFFSET) - 0.1  # the car's front into our back
    (hit,) = contacts_at(boxes, t, x, LANE0, 0.0, 8.0)
    assert (hit.kind, hit.at_fault) == ("rear", False)


@pytest.mark.parametrize(
    ("x", "y", "junction", "fault"),
    [
        (20.0, LANE0, False, False),  # inside lane 0: the other car's fault
        (20.0, -0.5, False, True),  # over the centre line: lanes 0 and -1
        (50.0, LANE0, True, True),  # front corners inside the junction
        (20.0, -9.0, False, True),  # the right flank over the kerb: off the driveable surface
    ],
)
def test_a_side_contact_is_at_fault_only_across_lanes_or_off_road(x, y, junction, fault):
    t = 1.0
    cx, cy = x + 0.1, y + 1.8  # a car alongside, 0.075 m into the ego's left flank
    world = _world([_obj("car", "vehicle.car", lambda s: (cx + 6.0 * (s - t), cy))], junction)
    (hit,) = contacts_at(SceneBoxes(world), t, x, y, 0.0, 6.0)
    assert (hit.kind, hit.at_fault) == ("side", fault)


def test_front_contacts_and_stopped_objects_are_at_fault():
    t = 1.0
    cone = _still("cone", "movable_object.trafficcone", 20.1, LANE0 + 1.1, size=(0.4, 0.4, 0.7))
    parked = _still("parked", "vehicle.car", 40.1, LANE0 - 1.8)
    world = _world([cone, parked])
    boxes = SceneBoxes(world)
    (hit,) = contacts_at(boxes, t, 20.0, LANE0, 0.0, 8.0)  # the cone on our left flank
    assert (hit.key, hit.kind, hit.at_fault, hit.agent) == ("cone", "stopped_object", True, False)
    (hit,) = contacts_at(boxes, t, 40.0, LANE0, 0.0, 8.0)  # a parked car: still a vehicle
    assert (hit.key, hit.kind, hit.at_fault, hit.agent) == ("parked", "stopped_object", True, True)
    assert [is_agent(c) for c in ("vehicle.bicycle", "human.pedestrian.adult",
                                  "movable_object.barrier", "static.manmade")] == [
        True, True, False, False
    ]  # fmt: skip
    with pytest.raises(ValueError, match="kind: expected one of"):
        contact_at_fault("head_on", False, False)


# ------------------------------------------------------------------ NC and the episode's end


def test_a_static_object_scores_nc_half_and_a_parked_car_zero():
    cone = _still("cone", "movable_object.trafficcone", 40.0, LANE0, size=(0.4, 0.4, 0.7))
    parked = _still("parked", "vehicle.car", 40.0, LANE0)
    for obj, nc in [(cone, 0.5), (parked, 0.0)]:
        world = _world([obj])
        ep = run_episode(world, _Cruise())
        assert ep.end == "collision" and ep.contact.key == obj.key and ep.contact.at_fault
        row = score_episode(world, ep)
        assert row["NC"] == nc and row["at_fault_collision"] and row["collided_with"] == obj.key
        assert row["PDMS"] == pytest.approx(nc * (5 * row["TTC"] + 5 * row["EP"] + 2 * row["C"])
                                            / 12)  # fmt: skip


def test_the_episode_goes_on_after_a_contact_it_is_not_at_fault_for():
    # A faster car in the ego lane runs into the ego's back at t = 4.46 s and drives on through.
    world = _world([_obj("car", "vehicle.car", lambda s: (-30.0 + 14.0 * s, LANE0))])
    ep = run_episode(world, _Cruise())
    assert ep.end == "scene_end" and ep.contact is None
    (hit,) = ep.not_at_fault_contacts
    assert (hit.key, hit.kind, hit.at_fault) == ("car", "rear", False)
    assert 3.0 < hit.t < 5.0 and ep.times[-1] == pytest.approx(world.duration)
    row = score_episode(world, ep)
    assert (row["NC"], row["collision"], row["at_fault_collision"]) == (1.0, True, False)
    assert (row["not_at_fault_contacts"], row["not_at_fault_with"]) == (1, "car")


# ------------------------------------------------------------------ TTC


@pytest.mark.parametrize(("gap", "ttc"), [(2.5, 0.0), (8.5, 0.0), (9.5, 1.0)])
def test_ttc_projects_the_ego_up_to_0_9_s(gap, ttc):
    x = 20.0  # rear axle of the last state; a parked car `gap` metres ahead of the bumper
    world = _world([_still("parked", "vehicle.car", x + FRONT + gap + 2.3, LANE0)])
    row = score_episode(world, _episode(_drive(x, LANE0, 10.0)))
    assert row["TTC"] == ttc  # 10 m/s: 3, 6, 9 m ahead at 0.3, 0.6, 0.9 s


def test_ttc_follows_the_logged_motion_not_a_constant_velocity():
    t, x = 2.1, 20.0  # the state's time and rear axle

    # Stands in lane 1 until t + 0.1, then pulls into our lane within 0.4 s: CV (at rest) misses.
    def pull_out(s):
        u = np.clip((s - t - 0.1) / 0.4, 0.0, 1.0)
        return (x + 8.0, -5.0 + u * (LANE0 + 5.0))

    # Walks towards our lane at 3 m/s, stops short of our box at t + 0.05: CV would walk on.
    def ped(s):
        return (x + 6.0, -3.2 + 3.0 * (min(s, t + 0.05) - t))

    walker = _obj("ped", "human.pedestrian.adult", ped, size=(0.6, 0.6, 1.75))
    for obj, ttc in [(_obj("car", "vehicle.car", pull_out), 0.0), (walker, 1.0)]:
        row = score_episode(_world([obj]), _episode(_drive(x, LANE0, 10.0)))
        assert row["TTC"] == ttc, obj.key


@pytest.mark.parametrize(("y", "ttc"), [(LANE0, 1.0), (-0.3, 0.0)])
def test_ttc_looks_in_a_30_degree_cone_unless_the_ego_straddles_lanes(y, ttc):
    x, t = 20.0, 2.1
    # An oncoming car 0.075 m into our lane: in our projected box at +0.3 s, its centre 36
    # degrees off our heading. In lane 0 that is not ahead; across the centre line it counts.
    car = _obj("car", "vehicle.car", lambda s: (x + 5.5 - 10.0 * (s - t), y + 1.8), yaw=np.pi)
    row = score_episode(_world([car]), _episode(_drive(x, y, 10.0)))
    assert row["TTC"] == ttc


@pytest.mark.parametrize(("speed", "ttc"), [(0.004, 1.0), (0.006, 0.0)])
def test_ttc_ignores_a_stopped_ego(speed, ttc):
    x, t = 20.0, 2.1  # an oncoming car in our lane, 2 m from our bumper
    car = _obj("car", "vehicle.car", lambda s: (x + FRONT + 4.3 - 10.0 * (s - t), LANE0), yaw=np.pi)
    row = score_episode(_world([car]), _episode(_drive(x, LANE0, speed)))
    assert row["TTC"] == ttc


def test_ttc_leaves_out_objects_of_earlier_not_at_fault_contacts():
    x = 20.0
    car = _still("parked", "vehicle.car", x + FRONT + 4.0, LANE0, moving=True)
    earlier = Contact("parked", "vehicle.car", False, "stopped_ego", True, 2.0)
    world = _world([car])
    assert score_episode(world, _episode(_drive(x, LANE0, 10.0)))["TTC"] == 0.0
    assert score_episode(world, _episode(_drive(x, LANE0, 10.0), contacts=[earlier]))["TTC"] == 1.0


# ------------------------------------------------------------------ comfort


def _states_from_speed(v, yaw=None):
    v = np.asarray(v, dtype=np.float64)
    yaw = np.zeros(len(v)) if yaw is None else yaw
    x = np.concatenate([[0.0], np.cumsum(v[1:] * DT)])
    return np.stack([x, np.zeros(len(v)), yaw, v], 1)


def _speed(acc, v0):
    return v0 + np.concatenate([[0.0], np.cumsum(np.asarray(acc)[1:] * DT)])


def test_comfort_windows_slide_every_plan_and_cover_the_end():
    assert comfort_windows(86) == [(a, a + 41) for a in range(0, 46, 5)]
    assert comfort_windows(50) == [(0, 41), (5, 46), (9, 50)]
    assert comfort_windows(30) == [(0, 30)] and comfort_windows(0) == []
    with pytest.raises(ValueError, match="stride: expected at least 1"):
        comfort_windows(50, stride=0)


def test_an_abrupt_3_m_s2_braking_is_comfortable_after_navsim_smoothing():
    # Cruise, brake at 3 m/s^2 for 3 s (a step in acceleration: 30 m/s^3 between two states,
    # 6 m/s^3 after a 0.5 s moving average), cruise: NAVSIM's filters pass it.
    acc = np.zeros(86)
    acc[30:60] = -3.0
    assert comfort_violations(_states_from_speed(_speed(acc, 12.0))) == dict.fromkeys(
        COMFORT_BOUNDS, 0
    )


def test_comfort_is_judged_in_4_s_windows_not_over_the_episode():
    # A 1.5 s braking at 5 m/s^2 mid-episode: a quadratic fit over the whole 8.5 s (what one
    # window over the episode would do) averages it to -1.9 m/s^2; a 4 s window does not.
    acc = np.zeros(86)
    acc[40:55] = -5.0
    states = _states_from_speed(_speed(acc, 15.0))
    assert comfort_signals(states)["lon_accel"].min() > COMFORT_BOUNDS["lon_accel"][0]
    bad = comfort_violations(states)
    assert bad["lon_accel"] > 0 and bad["lat_accel"] == bad["yaw_rate"] == 0


def test_the_jerk_magnitude_bound_8_37():
    # A 0.7 s swerve at 20 m/s, lateral acceleration growing as t^2 to 4.5 m/s^2: only the jerk
    # magnitude (11.6 m/s^3 at the end) leaves its bound.
    n, m = 8, 4.5
    t, tt = DT * np.arange(n), DT * (n - 1)
    yaw = m * t**3 / (3 * 20.0 * tt**2)
    bad = comfort_violations(_states_from_speed(np.full(n, 20.0), yaw))
    assert COMFORT_BOUNDS["jerk"] == (-8.37, 8.37)
    assert bad["jerk"] > 0 and sum(bad.values()) == bad["jerk"]
    assert comfort_violations(_states_from_speed(np.full(4, 20.0))) == dict.fromkeys(
        COMFORT_BOUNDS, 0
    )  # under 0.4 s: not judged
    with pytest.raises(ValueError, match=r"states: expected shape \[\.\.\., n >= 5, 4\]"):
        comfort_signals(np.zeros((4, 4)))


# ------------------------------------------------------------------ EP against the best episode


def _row(scene, progress, nc=1.0, dac=1.0, failed=False, planner="p"):
    return {"scene": scene, "planner": planner, "NC": nc, "DAC": dac, "TTC": 1.0, "C": 1.0,
            "failed": failed, "progress_m": progress}  # fmt: skip


def test_ep_best_divides_by_the_best_collision_free_on_road_episode():
    rows = [
        _row("a", 50.0, planner="log_replay"),
        _row("a", 60.0),  # the best that qualifies
        _row("a", 70.0, nc=0.5),  # hit a cone
        _row("a", 80.0, dac=0.0),  # left the road
        _row("a", 90.0, failed=True),
        _row("b", 3.0),  # scene b: nobody drove 5 m
        _row("b", 1.0),
    ]
    add_best_progress(rows)
    assert [r["EP_best"] for r in rows] == [0.833333, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]
    assert rows[0]["PDMS_best"] == pytest.approx((5 + 5 * 0.833333 + 2) / 12)
    assert rows[2]["PDMS_best"] == pytest.approx(0.5) and rows[4]["PDMS_best"] == 0.0
    with pytest.raises(ValueError, match="rows: expected score_episode rows"):
        add_best_progress([{"scene": "a"}])


def test_the_runner_adds_ep_best_over_every_planner(tmp_path):
    world = _world()  # an empty road: the faster planner drives farther than the log
    run = run_closed_loop([world], [make_planner("log_replay"), _Cruise(10.0, "fast")],
                          progress=False)  # fmt: skip
    log, fast = run.rows
    assert log["EP"] == 1.0 and fast["EP"] == 1.0  # against the log: clipped
    assert fast["EP_best"] == 1.0 and log["EP_best"] == pytest.approx(
        log["progress_m"] / fast["progress_m"], abs=1e-6
    )
    assert 0.75 < log["EP_best"] < 0.85 and log["PDMS_best"] < log["PDMS"]
    paths = write_outputs(run, [world], tmp_path, {}, [])
    head = paths["csv"].read_text().splitlines()[0].split(",")
    assert {"EP_best", "PDMS_best", "not_at_fault_contacts", "comfort_jerk"} <= set(head)
    assert "EP_best" not in paths["md"].read_text()
