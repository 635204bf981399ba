"""Unit checks of the simulator's geometry: overlap tests, voxeliser exactness, sensor rig."""

from __future__ import annotations

import numpy as np
import pytest

from renderworld.constants import FREE_ID, OCC3D_GRID
from renderworld.geometry import VoxelGrid
from renderworld.sim.agents import Path, Trajectory, rects_overlap
from renderworld.sim.objects import make_object
from renderworld.sim.occupancy import Voxeliser
from renderworld.sim.sensors import SensorRig, camera_time_offsets


def test_rects_overlap_hand_cases():
    half = np.array([2.0, 1.0])
    assert rects_overlap([0, 0], 0.0, half, [3.9, 0], 0.0, half)
    assert not rects_overlap([0, 0], 0.0, half, [4.1, 0], 0.0, half)
    # Rotated by 90°: extends 1 m along x, so 3.1 m apart no longer overlaps.
    assert not rects_overlap([0, 0], 0.0, half, [3.1, 0], np.pi / 2, half)
    assert rects_overlap([0, 0], 0.0, half, [2.9, 0], np.pi / 2, half)
    # Diagonal corner case at 45°: corner reaches sqrt(2) * 1.
    sq = np.array([1.0, 1.0])
    assert not rects_overlap([0, 0], np.pi / 4, sq, [2.5, 0], 0.0, sq)
    assert rects_overlap([0, 0], np.pi / 4, sq, [2.3, 0], 0.0, sq)


def test_path_offset_and_lookup():
    p = Path(np.array([[0.0, 0.0], [10.0, 0.0]]))
    assert p.length == pytest.approx(10.0)
    q = p.offset(-1.75)
    xy, heading = q.at(np.array([5.0]))
    np.testing.assert_allclose(xy, [[5.0, -1.75]], atol=1e-9)
    assert heading[0] == pytest.approx(0.0)
    with pytest.raises(ValueError, match=r"points: expected shape \[P>=2, 2\]"):
        Path(np.zeros((1, 2)))


class _World:  # the attributes Voxeliser.semantics reads
    def __init__(self, objects):
        from renderworld.sim.roads import GroundRaster, Road, RoadNetwork

        self.objects = objects
        net = RoadNetwork([Road(np.array([[-100.0, 0.0], [100.0, 0.0]]), lanes=1)])
        self.raster = GroundRaster(net, (-50, -50, 50, 50), cell=0.2)


@pytest.fixture(scope="module")
def voxeliser():
    return Voxeliser(SensorRig.build(64, 36), 256, (32, 18))


def test_box_voxelisation_is_exact(voxeliser):
    times = np.array([-1.0, 10.0])
    rng = np.random.default_rng(0)
    # A 2.0 x 1.2 x 1.0 barrier box whose faces sit strictly inside voxels.
    obj = make_object("b", "movable_object.barrier", (1.2, 2.0, 0.9),
                      Trajectory.fixed(times, 10.1, 5.1, 0.0), rng)  # fmt: skip
    sem = voxeliser.semantics(_World([obj]), 0.0, np.eye(4))
    grid = VoxelGrid(OCC3D_GRID)
    c = grid.centres()
    lo, hi = np.array([9.1, 4.5, 0.0]), np.array([11.1, 5.7, 0.9])
    half = grid.voxel_size / 2
    expect = ((c + half > lo) & (c - half < hi)).all(-1)
    got = sem == 1  # barrier
    assert (got == expect).all() and got.sum() == 6 * 4 * 3
    # Ground layer (voxel k=2 holds z=0): road on the centreline, terrain far away.
    assert sem[100, 100, 2] == 11 and sem[0, 0, 2] == 14 and sem[100, 100, 8] == FREE_ID


def test_tree_sphere_and_trunk_voxelised(voxeliser):
    rng = np.random.default_rng(0)
    tree = make_object("t", "static.vegetation", (3.0, 3.0, 7.0),
                       Trajectory.fixed(np.array([-1.0, 10.0]), -20.0, 15.0, 0.0), rng,
                       variant="tree")  # fmt: skip
    sem = voxeliser.semantics(_World([tree]), 0.0, np.eye(4))
    i, j = np.nonzero((sem == 16).any(-1))
    x = OCC3D_GRID.range_min[0] + (i + 0.5) * 0.4
    y = OCC3D_GRID.range_min[1] + (j + 0.5) * 0.4
    assert np.hypot(x + 20.0, y - 15.0).max() <= 1.5 + 0.3  # within the crown radius (+ voxel)
    assert (sem == 16).sum() > 50


def test_camera_offsets_within_a_sweep():
    off = camera_time_offsets(SensorRig.build(400, 225))
    assert len(set(off.values())) == 6 and all(0 < v < 50_000 for v in off.values())


def test_rig_rejects_bad_size():
    with pytest.raises(ValueError, match="image size: expected positive width/height"):
        SensorRig.build(0, 225)
