import math

import numpy as np
import pytest

from renderworld.constants import FREE_ID, GridSpec
from renderworld.metrics import (
    COLLISION_BEV_GRID,
    box_cells,
    collisions_with_boxes,
    collisions_with_occupancy,
    rasterize_boxes,
    trajectory_headings,
)

SMALL = GridSpec("small", (-10.0, -10.0, 0.0), (10.0, 10.0, 2.0), (40, 40, 2))  # 0.5 m


def test_headings_follow_travel_and_hold_when_standing():
    traj = np.array([[1.0, 0.0], [1.0, 1.0], [1.0, 1.0], [0.0, 1.0]])
    np.testing.assert_allclose(trajectory_headings(traj), [0, math.pi / 2, math.pi / 2, math.pi])
    np.testing.assert_allclose(trajectory_headings(np.zeros((2, 2))), [0.0, 0.0])


def test_ego_box_cell_count_and_rotation():
    ix, iy = box_cells(0.0, 0.0, 4.084, 1.85, 0.0, COLLISION_BEV_GRID)
    cells = set(zip(ix.tolist(), iy.tolist()))
    # 8 x 4 cell centres inside (|x| <= 2.04, |y| <= 0.925) + the length-wise centre line
    # (on the row boundary y = 0) reaching into columns 95 and 104 of rows 99 and 100.
    assert len(cells) == 36 and {(95, 99), (95, 100), (104, 99), (104, 100)} <= cells
    assert np.ptp(ix) == 9 and np.ptp(iy) == 3
    ix, iy = box_cells(0.0, 0.0, 4.084, 1.85, math.pi / 2, COLLISION_BEV_GRID)
    assert np.ptp(ix) == 3 and np.ptp(iy) == 9
    # A box smaller than a cell still marks the cell holding its centre.
    ix, iy = box_cells(0.1, 0.1, 0.05, 0.05, 0.3, COLLISION_BEV_GRID)
    assert set(ix.tolist()) == {100} and set(iy.tolist()) == {100}
    # A thin 0.2 m wide box between cell centres keeps its centre line.
    ix, iy = box_cells(0.0, 0.7, 2.9, 0.2, 0.0, COLLISION_BEV_GRID)  # y in [0.6, 0.8]
    assert set(iy.tolist()) == {101} and set(ix.tolist()) == set(range(97, 103))
    # Entirely outside the raster: no cell.
    assert box_cells(80.0, 0.0, 4.0, 2.0, 0.0, COLLISION_BEV_GRID)[0].size == 0


def _segments_cross(p, q, a, b):
    def orient(o, x, y):
        return (x[0] - o[0]) * (y[1] - o[1]) - (x[1] - o[1]) * (y[0] - o[0])

    d1, d2 = orient(a, b, p), orient(a, b, q)
    d3, d4 = orient(p, q, a), orient(p, q, b)
    return d1 * d2 <= 0 and d3 * d4 <= 0


def _segment_meets_square(p, q, lo, r):
    """Reference: an end point inside the square, or the segment crosses one of its edges."""
    if any(lo[0] <= e[0] <= lo[0] + r and lo[1] <= e[1] <= lo[1] + r for e in (p, q)):
        return True
    corners = [lo, (lo[0] + r, lo[1]), (lo[0] + r, lo[1] + r), (lo[0], lo[1] + r)]
    return any(_segments_cross(p, q, corners[i], corners[(i + 1) % 4]) for i in range(4))


def test_rasterize_matches_reference_rule():
    rng = np.random.default_rng(0)
    boxes = np.column_stack(
        [rng.uniform(-8, 8, 6), rng.uniform(-8, 8, 6), rng.uniform(0.3, 5, 6),
         rng.uniform(0.1, 3, 6), rng.uniform(-math.pi, math.pi, 6)]
    )  # fmt: skip
    from renderworld.metrics.collision import BevGrid

    grid = BevGrid.from_grid_spec(SMALL)
    got = rasterize_boxes(boxes, grid)
    want = np.zeros_like(got)
    for x, y, length, width, yaw in boxes:
        c, s = math.cos(yaw), math.sin(yaw)
        lines = [
            ((x - c * length / 2, y - s * length / 2), (x + c * length / 2, y + s * length / 2)),
            ((x + s * width / 2, y - c * width / 2), (x - s * width / 2, y + c * width / 2)),
        ]
        for i in range(40):
            for j in range(40):
                lo = (-10 + 0.5 * i, -10 + 0.5 * j)
                u = c * (lo[0] + 0.25 - x) + s * (lo[1] + 0.25 - y)
                v = -s * (lo[0] + 0.25 - x) + c * (lo[1] + 0.25 - y)
                inside = abs(u) <= length / 2 and abs(v) <= width / 2
                if inside or any(_segment_meets_square(p, q, lo, 0.5) for p, q in lines):
                    want[i, j] = True
    np.testing.assert_array_equal(got, want)


def test_ego_heading_decides_collision():
    agent = np.array([[0.0, 5.6, 0.5, 0.5, 0.0]])  # 1.6 m ahead of (0, 4) along +y
    boxes = np.stack([np.array([[30.0, 30.0, 1.0, 1.0, 0.0]]), agent])  # [S=2, M=1, 5]
    along_y = np.array([[0.0, 2.0], [0.0, 4.0]])  # heading +y: box reaches y = 6.04
    along_x = np.array([[-2.0, 4.0], [0.0, 4.0]])  # heading +x: box reaches y = 4.93
    hit, ok = collisions_with_boxes(along_y, boxes)
    assert hit.tolist() == [False, True] and ok.all()
    hit, _ = collisions_with_boxes(along_x, boxes)
    assert hit.tolist() == [False, False]


def test_agent_rotation_decides_collision():
    traj = np.array([[0.0, 0.0]])  # ego box at the origin, heading 0
    long_x = np.array([[[3.5, 0.0, 4.0, 0.4, 0.0]]])  # reaches back to x = 1.5
    long_y = np.array([[[3.5, 0.0, 4.0, 0.4, math.pi / 2]]])  # spans x 3.3..3.7 only
    assert collisions_with_boxes(traj, long_x)[0].tolist() == [True]
    assert collisions_with_boxes(traj, long_y)[0].tolist() == [False]
    seven = np.array([[[3.5, 0.0, 0.9, 4.0, 0.4, 1.5, 0.0]]])  # (x, y, z, l, w, h, yaw)
    assert collisions_with_boxes(traj, seven)[0].tolist() == [True]


def test_padding_rows_need_a_mask():
    traj = np.array([[0.0, 0.0]])
    boxes = np.array([[[np.nan] * 5, [0.0, 0.0, 1.0, 1.0, 0.0]]])
    with pytest.raises(ValueError, match="boxes: expected finite values in valid rows"):
        collisions_with_boxes(traj, boxes)
    hit, _ = collisions_with_boxes(traj, boxes, box_valid=np.array([[False, True]]))
    assert hit.tolist() == [True]
    hit, _ = collisions_with_boxes(traj, boxes, box_valid=np.array([[False, False]]))
    assert hit.tolist() == [False]


def test_occupancy_collision_objects_only_and_frame_poses():
    occ = np.full((1, *SMALL.shape), FREE_ID, dtype=np.uint8)
    occ[0, 20, 20, 1] = 4  # car voxel at (0.25, 0.25) in that frame's own ego frame
    occ[0, 28, 20, 0] = 11  # road at (4.25, 0.25): never a collision
    traj = np.array([[3.0, 0.0]])
    hit, ok = collisions_with_occupancy(traj, occ, SMALL)  # occupancy read as current frame
    assert hit.tolist() == [False] and ok.all()
    # The frame sits at (3, 0) in the current frame: the car is at (3.25, 0.25) there.
    hit, _ = collisions_with_occupancy(traj, occ, SMALL, frame_poses=np.array([[3.0, 0.0, 0.0]]))
    assert hit.tolist() == [True]
    # A frame rotated by +90 deg: current (0, 3) is (3, 0) in it; no object there.
    hit, _ = collisions_with_occupancy(
        np.array([[0.0, 3.0]]), occ, SMALL, frame_poses=np.array([[0.0, 0.0, math.pi / 2]])
    )
    assert hit.tolist() == [False]
    occ[0, 26, 20, 0] = 7  # pedestrian at (3.25, 0.25) in the rotated frame
    hit, _ = collisions_with_occupancy(
        np.array([[0.0, 3.0]]), occ, SMALL, frame_poses=np.array([[0.0, 0.0, math.pi / 2]])
    )
    assert hit.tolist() == [True]
    hit, ok = collisions_with_occupancy(np.array([[30.0, 0.0]]), occ, SMALL)
    assert not ok[0] and not hit[0]
    with pytest.raises(ValueError, match="occupancy: expected"):
        collisions_with_occupancy(traj, occ[:, :10], SMALL)


def test_several_trajectories_equal_one_by_one():
    rng = np.random.default_rng(2)
    boxes = np.column_stack(
        [rng.uniform(-6, 6, (4 * 3,)), rng.uniform(-6, 6, 12), rng.uniform(1, 5, 12),
         rng.uniform(0.5, 2, 12), rng.uniform(-3, 3, 12)]
    ).reshape(4, 3, 5)  # fmt: skip
    trajs = np.cumsum(rng.uniform(-2, 3, (5, 4, 2)), axis=1)
    hit, ok = collisions_with_boxes(trajs, boxes)
    assert hit.shape == (5, 4) and hit.any() and not hit.all()
    for j in range(5):
        h1, o1 = collisions_with_boxes(trajs[j], boxes)
        np.testing.assert_array_equal(hit[j], h1)
        np.testing.assert_array_equal(ok[j], o1)
    occ = np.full((4, *SMALL.shape), FREE_ID, dtype=np.uint8)
    occ[:, 15:25, 15:25, 0] = 4
    hit, _ = collisions_with_occupancy(trajs, occ, SMALL)
    for j in range(5):
        np.testing.assert_array_equal(hit[j], collisions_with_occupancy(trajs[j], occ, SMALL)[0])
