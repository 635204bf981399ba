"""LiDAR -> label map: hand-computed projection, pixel rule, z-buffer, the devkit chain."""

import numpy as np
import pytest
import transforms3d

from data_converters import CameraView, PointSource, label_maps, project_to_label_map
from data_converters.fast_index import TableIndex
from data_converters.labels import point_sources
from data_converters.sample_infos import camera_views, scene_frames
from renderworld.constants import CAMERA_NAMES
from renderworld.data import IGNORE_LABEL, DatasetError, NuScenesReader
from renderworld.data.labels2d import zbuffer_nearest
from tests.converter.datasets_for_tests import VERSION
from tests.converter.oracle import as_dict, keyframe_record, load_raw, oracle_labels

K = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
EYE = np.eye(4)


def project(points, labels, size=(80, 100), label_size=(40, 50), l2c=EYE, min_depth=1.0):
    pts = np.asarray(points, dtype=np.float64)
    return project_to_label_map(
        pts, np.asarray(labels, np.uint8), l2c, K, size, label_size, min_depth
    )


def test_hand_computed_point_and_pixel_rule():
    # (1, 0.5, 10) -> u = 100 * 0.1 + 50 = 60, v = 100 * 0.05 + 40 = 45; at scale 0.5:
    # pixel (floor(30), floor(22.5)) = (30, 22).
    lab = project([[1.0, 0.5, 10.0]], [4])
    assert (lab.u.tolist(), lab.v.tolist()) == ([30], [22])
    assert lab.depth.tolist() == [10.0] and lab.label.tolist() == [4]
    assert (lab.height, lab.width) == (40, 50)
    assert (lab.u.dtype, lab.v.dtype, lab.depth.dtype, lab.label.dtype) == (
        np.uint16,
        np.uint16,
        np.float32,
        np.uint8,
    )
    # u just below 60 -> 59.99.. * 0.5 floors to 29; full resolution keeps the floor too.
    lab = project([[0.9999, 0.5, 10.0]], [4])
    assert lab.u.tolist() == [29]
    full = project([[0.9999, 0.5, 10.0]], [4], label_size=(80, 100))
    assert (full.u.tolist(), full.v.tolist()) == ([59], [45])


def test_hand_computed_with_transform():
    # LiDAR frame rotated 90 deg about the camera's y axis and shifted: camera = R p + t.
    l2c = np.eye(4)
    l2c[:3, :3] = transforms3d.euler.euler2mat(0, np.pi / 2, 0)  # x_lidar -> -z? check below
    l2c[:3, 3] = [0.5, 0.0, 2.0]
    p = np.array([[-8.0, 0.0, 0.0]])
    cam = l2c[:3, :3] @ p[0] + l2c[:3, 3]
    u = 100 * cam[0] / cam[2] + 50
    v = 100 * cam[1] / cam[2] + 40
    assert cam[2] > 1
    lab = project(p, [7], label_size=(80, 100), l2c=l2c)
    assert (lab.u.tolist(), lab.v.tolist()) == ([int(np.floor(u))], [int(np.floor(v))])
    assert lab.depth[0] == pytest.approx(cam[2], rel=1e-6)


def test_behind_outside_and_near_points_are_dropped():
    pts = [
        [0.0, 0.0, -5.0],  # behind the camera
        [0.0, 0.0, 0.5],  # in front but closer than 1 m
        [0.0, 0.0, 1.0],  # exactly 1 m: the devkit keeps depth > 1 only
        [6.0, 0.0, 10.0],  # u = 110 >= W = 100
        [-5.1, 0.0, 10.0],  # u = -1 < 0
        [0.0, 4.1, 10.0],  # v = 81 >= H = 80
        [4.99, 3.99, 10.0],  # u = 99.9, v = 79.9: inside, last pixel
    ]
    lab = project(pts, [1, 2, 3, 4, 5, 6, 9], label_size=(80, 100))
    assert lab.label.tolist() == [9]
    assert (lab.u.tolist(), lab.v.tolist()) == ([99], [79])


def test_zbuffer_keeps_nearest_on_one_pixel_ray():
    ray = np.array([0.305, -0.195, 1.0])  # pixel centre (80.5, 20.5)
    pts = [ray * 20, ray * 5, ray * 12, [0.0, 0.0, 30.0]]  # three on one ray, farthest first
    lab = project(pts, [15, 4, 16, 11], label_size=(80, 100))
    assert len(lab) == 2
    on_ray = lab.label != 11
    assert lab.label[on_ray].tolist() == [4]
    assert lab.depth[on_ray][0] == pytest.approx(5.0)


def zbuffer_reference(pixel, depth):
    """Loop reference of the vectorised z-buffer (nearest per pixel, earliest on ties)."""
    best = {}
    for i, (p, d) in enumerate(zip(pixel.tolist(), depth.tolist())):
        if p not in best or d < depth[best[p]]:
            best[p] = i
    return np.array([best[p] for p in sorted(best)], dtype=np.int64)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_zbuffer_matches_loop_reference(seed):
    rng = np.random.default_rng(seed)
    pixel = rng.integers(0, 30, 400)
    depth = rng.integers(1, 6, 400).astype(np.float64)  # many exact ties
    np.testing.assert_array_equal(zbuffer_nearest(pixel, depth), zbuffer_reference(pixel, depth))
    assert zbuffer_nearest(np.zeros(0, int), np.zeros(0)).shape == (0,)


def test_zbuffer_validates():
    with pytest.raises(ValueError, match="pixel/depth: expected two"):
        zbuffer_nearest(np.zeros(3, int), np.zeros(2))


def test_sources_are_motion_compensated_through_their_own_ego_pose():
    # A static world point seen by two sweeps taken from different ego poses must land on the
    # same pixel: each sweep is mapped lidar -> ego -> global with its own pose.
    world = np.array([30.0, 2.0, 1.0])
    cam_to_ego = np.array([[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])
    cam = CameraView(K, cam_to_ego, np.eye(4), (80, 100), (80, 100))
    sources = []
    for x, yaw, label in ((0.0, 0.0, 4), (3.0, 0.1, 7)):
        ego = np.eye(4)
        ego[:3, :3] = transforms3d.euler.euler2mat(0, 0, yaw)
        ego[:3, 3] = [x, 0.0, 0.0]
        local = np.linalg.inv(ego) @ np.r_[world, 1.0]
        sources.append(PointSource(local[None, :3], np.array([label], np.uint8), np.eye(4), ego))
    single = [label_maps([s], [cam])[0] for s in sources]
    assert (single[0].u[0], single[0].v[0]) == (single[1].u[0], single[1].v[0])
    both = label_maps(sources, [cam])[0]
    assert len(both) == 1 and both.depth[0] == pytest.approx(30.0)
    # Move the second sweep's point 1 m farther along the same camera ray: the first must win.
    far = sources[1].ego_to_global @ np.r_[sources[1].points[0], 1.0]
    far[:3] = world + (world - cam_to_ego[:3, 3]) / np.linalg.norm(world) * 1.0
    local = np.linalg.inv(sources[1].ego_to_global) @ far
    sources[1] = PointSource(
        local[None, :3], sources[1].labels, np.eye(4), sources[1].ego_to_global
    )
    assert label_maps(sources, [cam])[0].label.tolist() == [4]
    assert label_maps(sources[::-1], [cam])[0].label.tolist() == [4]


def test_label_maps_follow_the_devkit_chain_on_a_moving_dataset(moving_raw):
    """Independent recomputation from the raw JSON records, step by step as the devkit does."""
    tables = TableIndex(NuScenesReader(moving_raw, VERSION))
    raw = load_raw(moving_raw, VERSION)
    frames = scene_frames(tables, "scene-0061", 0)
    token = frames.tokens[1]
    for label_hw in (None, (61, 102)):
        _, views = camera_views(tables, token, lambda hw, s=label_hw: s or hw)
        labels = label_maps(point_sources(tables, frames, 1), views)
        n_checked = 0
        for c, channel in enumerate(CAMERA_NAMES):
            lidar_ts = keyframe_record(raw, token, "LIDAR_TOP")["timestamp"]
            assert keyframe_record(raw, token, channel)["timestamp"] != lidar_ts
            expect = oracle_labels(moving_raw, raw, token, channel, label_hw)
            got = as_dict(labels[c])
            assert got.keys() == expect.keys(), channel
            for key, (depth, label) in expect.items():
                assert got[key][0] == pytest.approx(depth, rel=1e-6)
                assert got[key][1] == label
            n_checked += len(expect)
        assert n_checked > 300  # the points really land in the cameras


def test_sweeps_add_depth_only_points(moving_raw):
    tables = TableIndex(NuScenesReader(moving_raw, VERSION))
    frames = scene_frames(tables, "scene-0061", 0)
    key = point_sources(tables, frames, 1)
    with_sweeps = point_sources(tables, frames, 1, sweeps=2)
    assert len(key) == 1 and len(with_sweeps) == 5  # 2 before and 2 after the keyframe
    assert all((s.labels == IGNORE_LABEL).all() for s in with_sweeps[1:])
    ts = {tables.field(t, "timestamp") for t in tables.reader.table("sample_data").index}
    poses = {tuple(s.ego_to_global[:3, 3]) for s in with_sweeps}
    assert len(poses) == 5 and len(ts) > 5  # every sweep brings its own ego pose
    multi = point_sources(tables, frames, 1, multiframe=1)
    assert len(multi) == 3
    static = np.isin(multi[1].labels, [11, 12, 13, 14, 15, 16])
    assert static.all() and 0 < len(multi[1].labels) < len(key[0].labels)


def test_table_index_agrees_with_the_reader(moving_raw):
    reader = NuScenesReader(moving_raw, VERSION)
    tables = TableIndex(reader)
    for sd in reader.table("sample_data").index[::3]:
        np.testing.assert_array_equal(tables.sensor_to_ego(sd), reader.sensor_to_ego(sd))
        np.testing.assert_array_equal(tables.ego_to_global(sd), reader.ego_to_global(sd))
        assert tables.field(sd, "timestamp") == reader.timestamp(sd)
    for token in reader.table("sample").index:
        ours, theirs = tables.sample_boxes(token), reader.sample_boxes(token)
        for col in ours.columns:
            np.testing.assert_array_equal(ours[col].to_numpy(), theirs[col].to_numpy())
    with pytest.raises(DatasetError, match=r"sample_data.json: no record with token 'nope'"):
        tables.field("nope", "filename")
