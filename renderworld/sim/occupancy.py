"""Occ3D ground truth: semantics from the scene geometry, LiDAR and camera visibility masks.

Semantics [X, Y, Z] uint8 in the ego frame (Occ3D classes, free = ``FREE_ID``): the ground
layer takes the majority ground class of 3x3 samples per column; every solid primitive marks
each voxel it intersects (exact box/cylinder/sphere vs voxel tests, closed sets), static
structure first and objects last. ``mask_lidar`` marks voxels a returned LiDAR ray reaches
(traversed or hit); ``mask_camera`` the voxels of ``mask_lidar`` in front of the first surface
seen by some camera. The sensors are fixed in the ego frame, so each voxel's beam, azimuth bin
and camera pixel are precomputed once.
"""

from __future__ import annotations

import numpy as np

from renderworld.constants import (
    CAMERA_NAMES,
    FREE_ID,
    LIDAR_NAME,
    LIDARSEG_TO_OCC3D,
    OCC3D_GRID,
    GridSpec,
)
from renderworld.geometry import VoxelGrid, invert_pose, scale_intrinsics
from renderworld.sim.agents import rects_overlap
from renderworld.sim.layout import World
from renderworld.sim.objects import BOX, SPHERE
from renderworld.sim.sensors import SensorRig, lidar_beams, xform

__all__ = ["SemanticVoxeliser", "Voxeliser"]

_LUT = np.array([LIDARSEG_TO_OCC3D[i] for i in range(32)], dtype=np.uint8)
_EPS = 1e-4


class SemanticVoxeliser:
    """Occ3D semantics of a world on one grid (no sensors: what a planner reads).

    Args:
        grid: the voxel grid (default Occ3D 200x200x16, 0.4 m).
    """

    def __init__(self, grid: GridSpec = OCC3D_GRID):
        self.grid = VoxelGrid(grid)
        col = self.grid.centres()[:, :, 0, :2]
        sub = (np.arange(3) - 1) * self.grid.voxel_size[0] / 3
        self._ground_xy = (col[:, :, None, None, :] + np.stack(np.meshgrid(sub, sub), -1)).reshape(
            -1, 2
        )
        self._ground_k = int(np.floor((0.0 - self.grid.range_min[2]) / self.grid.voxel_size[2]))

    # ------------------------------------------------------------------ semantics
    def semantics(self, world: World, t: float, ego_pose: np.ndarray) -> np.ndarray:
        """[X, Y, Z] uint8 Occ3D classes at time ``t`` (ego pose [4, 4] ego→scene)."""
        X, Y, Z = self.grid.shape
        sem = np.full((X, Y, Z), FREE_ID, dtype=np.uint8)
        if 0 <= self._ground_k < Z:
            g, m = self._ground_xy, ego_pose
            xy = np.stack([g[:, 0] * m[0, 0] + g[:, 1] * m[0, 1] + m[0, 3],
                           g[:, 0] * m[1, 0] + g[:, 1] * m[1, 1] + m[1, 3]], 1)  # fmt: skip
            cls = world.raster.classify(xy).reshape(X * Y, 9)
            counts = np.stack([(cls == c).sum(1) for c in (24, 26, 27)], 1)
            best = np.array([24, 26, 27], dtype=np.uint8)[counts.argmax(1)]
            sem[:, :, self._ground_k] = _LUT[best].reshape(X, Y)
        to_ego = invert_pose(ego_pose)
        ego_yaw = float(np.arctan2(ego_pose[1, 0], ego_pose[0, 0]))
        order = sorted(range(len(world.objects)), key=lambda i: world.objects[i].label < 28)
        for i in order:
            obj = world.objects[i]
            (xy, yaw) = obj.trajectory.pose(t)
            c_obj = to_ego[:2, :2] @ xy + to_ego[:2, 3]
            yaw_e = float(yaw) - ego_yaw
            rot = np.array([[np.cos(yaw_e), -np.sin(yaw_e)], [np.sin(yaw_e), np.cos(yaw_e)]])
            if np.abs(c_obj).max() > 40.0 + np.hypot(*obj.size[:2]):
                continue
            cls = _LUT[obj.label]
            for k in range(len(obj.shape)):
                centre = np.concatenate([rot @ obj.centre[k, :2] + c_obj, obj.centre[k, 2:]])
                self._mark(sem, int(obj.shape[k]), centre, obj.dims[k], yaw_e + obj.yaw[k], cls)
        return sem

    def _mark(self, sem, shape, centre, dims, yaw, cls) -> None:
        g = self.grid
        vs = g.voxel_size
        if shape == BOX:
            c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
            ext_xy = np.array([c * dims[0] + s * dims[1], s * dims[0] + c * dims[1]]) / 2
            z0, z1 = centre[2] - dims[2] / 2, centre[2] + dims[2] / 2
        else:  # cylinders and cones (their bounding cylinder), spheres
            ext_xy = np.array([dims[0], dims[1]]) / 2
            z0 = centre[2] - dims[2] / 2 if shape != 3 else centre[2]
            z1 = z0 + dims[2]
        lo = np.floor((np.r_[centre[:2] - ext_xy, z0] - g.range_min) / vs - _EPS).astype(int)
        hi = np.floor((np.r_[centre[:2] + ext_xy, z1] - g.range_min) / vs + _EPS).astype(int)
        lo, hi = np.maximum(lo, 0), np.minimum(hi, np.asarray(g.shape) - 1)
        if (hi < lo).any():
            return
        ii, jj = np.meshgrid(
            np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), indexing="ij"
        )
        vc = g.range_min[:2] + (np.stack([ii, jj], -1) + 0.5) * vs[:2]
        ks = np.arange(lo[2], hi[2] + 1)
        zc = g.range_min[2] + (ks + 0.5) * vs[2]
        if shape == BOX:
            cols = rects_overlap(centre[:2], yaw, dims[:2] / 2 + _EPS, vc, 0.0, vs[:2] / 2)
            sem[ii[cols][:, None], jj[cols][:, None], ks[None]] = cls
            return
        dx = np.maximum(np.abs(vc - centre[:2]) - vs[:2] / 2, 0)
        d2 = (dx**2).sum(-1)
        r = dims[0] / 2 + _EPS
        if shape == SPHERE:
            dz = np.maximum(np.abs(zc - centre[2]) - vs[2] / 2, 0)
            hit = d2[..., None] + dz**2 <= r * r
            a, b, k = np.nonzero(hit)
            sem[ii[a, b], jj[a, b], ks[k]] = cls
            return
        cols = d2 <= r * r
        sem[ii[cols][:, None], jj[cols][:, None], ks[None]] = cls


class Voxeliser(SemanticVoxeliser):
    """Occ3D labels for one sensor rig and grid: semantics plus the LiDAR and camera masks.

    Args:
        rig: sensor calibrations.
        azimuth_steps: LiDAR rays per beam per revolution.
        mask_size: (w, h) of the camera depth maps used for ``mask_camera``.
        grid: the voxel grid (default Occ3D 200x200x16, 0.4 m).
    """

    def __init__(self, rig: SensorRig, azimuth_steps: int, mask_size, grid: GridSpec = OCC3D_GRID):
        super().__init__(grid)
        self.rig = rig
        self.mask_size = mask_size
        centres = self.grid.centres().reshape(-1, 3)
        half = self.grid.voxel_size / 2
        # LiDAR: nearest beam and azimuth bin of every voxel centre; covered if the beam
        # passes within the voxel's half size.
        q = xform(invert_pose(rig.sensor_to_ego[LIDAR_NAME]), centres)
        r = np.linalg.norm(q, axis=1)
        el = np.arcsin(np.clip(q[:, 2] / np.maximum(r, 1e-6), -1, 1))
        beams = lidar_beams()
        step = beams[1] - beams[0]
        b = np.clip(np.round((el - beams[0]) / step), 0, 31).astype(np.int64)
        covered = np.abs(el - beams[b]) * r <= half.max() * 1.2
        az = np.mod(np.arctan2(q[:, 1], q[:, 0]), 2 * np.pi)
        a = np.mod(np.round(az / (2 * np.pi / azimuth_steps)), azimuth_steps).astype(np.int64)
        self._l_idx = np.nonzero(covered)[0]
        self._l_flat = (b * azimuth_steps + a)[covered]
        self._l_r = r[covered].astype(np.float32)
        self._margin = float(np.linalg.norm(half))
        # Cameras: pixel of every voxel centre in each depth map.
        self._cams = []
        w, h = mask_size
        for ch in CAMERA_NAMES:
            K = scale_intrinsics(rig.intrinsics[ch], w / rig.width, h / rig.height)
            pc = xform(invert_pose(rig.sensor_to_ego[ch]), centres)
            z = pc[:, 2]
            zs = np.maximum(z, 1e-6)
            u = np.floor(K[0, 0] * pc[:, 0] / zs + K[0, 2]).astype(np.int64)
            v = np.floor(K[1, 1] * pc[:, 1] / zs + K[1, 2]).astype(np.int64)
            ok = (z > 0.1) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            idx = np.nonzero(ok)[0]
            self._cams.append((idx, (v * w + u)[ok], z[ok].astype(np.float32)))

    # ------------------------------------------------------------------ masks
    def mask_lidar(self, range_image: np.ndarray, points_ego: np.ndarray | None = None):
        """[X, Y, Z] uint8: voxels reached by returned LiDAR rays.

        Args:
            range_image: [32, A] true range (metres) of each kept return, -1 where none.
            points_ego: [N, 3] returned points in the ego frame; their voxels are marked too.
        """
        rng = range_image.reshape(-1)[self._l_flat]
        seen = (rng > 0) & (self._l_r <= rng + self._margin)
        out = np.zeros(self.grid.spec.num_voxels, dtype=np.uint8)
        out[self._l_idx[seen]] = 1
        if points_ego is not None and len(points_ego):
            idx, inside = self.grid.points_to_index(points_ego)
            out[self.grid.flat_index(idx[inside])] = 1
        return out.reshape(self.grid.shape)

    def mask_camera(self, depths: list[np.ndarray], mask_lidar: np.ndarray) -> np.ndarray:
        """[X, Y, Z] uint8: voxels of ``mask_lidar`` in front of the first surface of some camera.

        Args:
            depths: per camera (``CAMERA_NAMES`` order) z-depth maps [h, w] metres (inf = sky).
            mask_lidar: [X, Y, Z] uint8.
        """
        seen = np.zeros(self.grid.spec.num_voxels, dtype=bool)
        for (idx, pix, z), depth in zip(self._cams, depths):
            seen[idx] |= z <= depth.reshape(-1)[pix] + self._margin
        return (seen.reshape(self.grid.shape) & (mask_lidar > 0)).astype(np.uint8)
