"""Synthetic Img2Occ samples: a ground plane, a car-sized box and a wall on a small grid.

Cameras use the nuScenes n015 calibration (docs/formats.md#sensors-and-calibration) scaled to small
image sizes. Depth and semantic targets come from analytic ray marching through the GT voxels at
pixel centres (docs/conventions.md#pixels), thinned to mimic LiDAR; images are the class colours of
the first hit.
"""

from __future__ import annotations

import numpy as np
import torch

from renderworld.constants import FREE_ID, OCC3D_COLORS, GridSpec
from renderworld.geometry import VoxelGrid, pose_matrix

# (translation, rotation [w, x, y, z], fx, cx, cy) at 1600x900, CAMERA_NAMES order.
CALIB = (
    ((1.7008, 0.0160, 1.5110), (0.49980, -0.50303, 0.49978, -0.49737), 1266.4, 816.3, 491.5),
    ((1.5509, -0.4934, 1.4958), (0.20603, -0.20269, 0.68245, -0.67136), 1260.8, 808.0, 495.3),
    ((1.5239, 0.4946, 1.5093), (0.67573, -0.67363, 0.21214, -0.21123), 1272.6, 826.6, 479.8),
    ((0.0283, 0.0035, 1.5791), (0.50379, -0.49740, -0.49419, 0.50455), 809.2, 829.2, 481.8),
    ((1.0357, 0.4848, 1.5910), (0.69242, -0.70316, -0.11648, 0.11203), 1256.7, 792.1, 492.8),
    ((1.0149, -0.4806, 1.5624), (0.12281, -0.13240, -0.70043, 0.69050), 1259.5, 807.3, 501.2),
)

TEST_GRID = GridSpec("test", (-9.6, -9.6, -1.0), (9.6, 9.6, 2.2), (16, 16, 4))
GROUND, CAR, WALL = 11, 4, 15


def make_scene(grid: GridSpec = TEST_GRID) -> np.ndarray:
    """GT occupancy [X, Y, Z] uint8: ground layer, a car box ahead, a wall on the left."""
    g = VoxelGrid(grid)
    c = g.centres()
    occ = np.full(grid.shape, FREE_ID, dtype=np.uint8)
    occ[..., 0] = GROUND
    x, y, z = c[..., 0], c[..., 1], c[..., 2]
    occ[(x > 3.0) & (x < 7.5) & (np.abs(y) < 1.5) & (z > -0.2) & (z < 1.4)] = CAR
    occ[(x > -6.0) & (x < 6.0) & (y > 6.0) & (y < 7.5) & (z > -0.2)] = WALL
    return occ


def camera_intrinsics(ci: int, width: int, height: int) -> np.ndarray:
    """3x3 intrinsics of camera ``ci`` resized from 1600x900 to width x height."""
    _, _, f, cx, cy = CALIB[ci]
    sx, sy = width / 1600.0, height / 900.0
    return np.array([[f * sx, 0, cx * sx], [0, f * sy, cy * sy], [0, 0, 1]], dtype=np.float64)


def ray_cast(occ, grid, cam_to_ego, k, width, height, step=0.05, max_depth=16.0):
    """First occupied voxel along every pixel-centre ray.

    Returns:
        depth [H, W] camera z of the hit (0 = none), label [H, W] (255 = none),
        observed [X, Y, Z] bool voxels crossed by rays up to and including the hit.
    """
    g = VoxelGrid(grid)
    jj, ii = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    pix = np.stack([ii, jj, np.ones_like(ii)], -1).reshape(-1, 3)
    d_cam = pix @ np.linalg.inv(k).T  # z = 1: the march parameter is camera-z depth
    d_ego = d_cam @ cam_to_ego[:3, :3].T
    o = cam_to_ego[:3, 3]
    ts = np.arange(0.3, max_depth, step)
    pts = o[None, None] + d_ego[:, None] * ts[None, :, None]  # [R, S, 3]
    idx, inside = g.points_to_index(pts)
    lab = occ[idx[..., 0], idx[..., 1], idx[..., 2]]
    hit = inside & (lab != FREE_ID)
    first = np.where(hit.any(1), hit.argmax(1), -1)
    r = np.arange(len(first))
    has = first >= 0
    depth = np.where(has, ts[np.maximum(first, 0)], 0.0)
    label = np.where(has, lab[r, np.maximum(first, 0)], 255)
    observed = np.zeros(grid.shape, dtype=bool)
    upto = (np.arange(len(ts))[None] <= np.where(has, first, len(ts))[:, None]) & inside
    sel = idx[upto]
    observed[sel[:, 0], sel[:, 1], sel[:, 2]] = True
    return depth.reshape(height, width), label.reshape(height, width), observed


def make_sample(
    cameras=(0, 1, 2, 3, 4, 5),
    input_size=(48, 88),
    render_size=(18, 32),
    grid: GridSpec = TEST_GRID,
    lidar_keep: float = 0.7,
    seed: int = 0,
) -> dict:
    """One Img2OccDataset-format batch (B = 1) of the synthetic scene."""
    rng = np.random.default_rng(seed)
    occ = make_scene(grid)
    colours = np.asarray(OCC3D_COLORS, dtype=np.float32) / 255.0
    sky = np.array([0.5, 0.7, 1.0], dtype=np.float32)
    (hi, wi), (hr, wr) = input_size, render_size
    images, ks, rks, poses, depths, sems = [], [], [], [], [], []
    observed = np.zeros(grid.shape, dtype=bool)
    for ci in cameras:
        t, q, *_ = CALIB[ci]
        pose = pose_matrix(t, q)
        k_in, k_r = camera_intrinsics(ci, wi, hi), camera_intrinsics(ci, wr, hr)
        d_in, l_in, _ = ray_cast(occ, grid, pose, k_in, wi, hi)
        img = np.where((l_in == 255)[..., None], sky, colours[np.minimum(l_in, FREE_ID)])
        img = img * np.where(d_in > 0, 1.0 - 0.02 * d_in, 1.0)[..., None]
        d_r, l_r, obs = ray_cast(occ, grid, pose, k_r, wr, hr)
        observed |= obs
        keep = rng.random(d_r.shape) < lidar_keep
        depths.append(np.where(keep, d_r, 0.0))
        sems.append(np.where(keep & (l_r != 255), l_r, 255))
        images.append(np.clip(img, 0, 1).transpose(2, 0, 1))
        ks.append(k_in)
        rks.append(k_r)
        poses.append(pose)

    def t32(a):
        return torch.as_tensor(np.stack(a), dtype=torch.float32)[None]

    return {
        "images": t32(images),
        "intrinsics": t32(ks),
        "render_intrinsics": t32(rks),
        "cam_to_ego": t32(poses),
        "depth": t32(depths),
        "semantics": torch.as_tensor(np.stack(sems), dtype=torch.int64)[None],
        "occ": torch.as_tensor(occ)[None],
        "mask_camera": torch.as_tensor(observed)[None],
        "mask_lidar": torch.as_tensor(observed)[None],
        "meta": {"sample_token": ["synthetic-token-0"], "scene": ["scene-synthetic"]},
    }
