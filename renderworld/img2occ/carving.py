"""Free-space carving from the 2-D LiDAR depth maps (an option, not in the paper).

A camera pixel with LiDAR depth ``d`` says that its ray is empty up to ``d``. A voxel whose
centre projects into such a pixel at camera depth ``z < d - margin`` therefore lies in seen
free space. Rendered losses cannot tell a half-transparent veil of Gaussians in front of a
surface from the surface itself (the blended colour and the expected depth barely change),
so the readout fills free space in front of facades; this loss pushes the opacity of such
voxels to 0. It uses only the 2-D depth maps the renders are already compared with (the
voxels are projected into them, nothing is read from 3-D labels). A voxel that some camera
sees at its surface (``|z - d| <= margin``) is never carved.
"""

from __future__ import annotations

import torch

from renderworld.geometry import invert_pose, project_points

__all__ = ["free_space_targets", "free_space_loss"]


def free_space_targets(
    centres: torch.Tensor,
    cam_to_ego: torch.Tensor,
    intrinsics: torch.Tensor,
    depth: torch.Tensor,
    margin: float,
    near: float = 0.1,
) -> torch.Tensor:
    """Voxels seen free by at least one camera's LiDAR depth map and at no camera's surface.

    Args:
        centres: [V, 3] voxel centres, metres, ego frame.
        cam_to_ego: [B, C, 4, 4] camera → ego transforms.
        intrinsics: [B, C, 3, 3] intrinsics of the depth maps (pixels).
        depth: [B, C, H, W] LiDAR depth maps, metres camera z (0 = no point).
        margin: metres; free when ``z < d - margin``, surface when ``|z - d| <= margin``.
        near: voxel centres at camera z <= near are not seen.

    Returns:
        [B, V] bool.
    """
    b, c, h, w = depth.shape
    if cam_to_ego.shape != (b, c, 4, 4) or intrinsics.shape != (b, c, 3, 3):
        raise ValueError(
            f"cam_to_ego/intrinsics: expected [{b}, {c}, 4, 4] and [{b}, {c}, 3, 3], got "
            f"{tuple(cam_to_ego.shape)} and {tuple(intrinsics.shape)}"
        )
    if not margin > 0:
        raise ValueError(f"margin: expected > 0 metres, got {margin!r}")
    dtype = torch.float32
    centres = centres.to(device=depth.device, dtype=dtype)
    ego_to_cam = invert_pose(cam_to_ego.to(device=depth.device, dtype=dtype))
    free = torch.zeros(b, centres.shape[0], dtype=torch.bool, device=depth.device)
    surface = torch.zeros_like(free)
    for ci in range(c):
        rot, trans = ego_to_cam[:, ci, :3, :3], ego_to_cam[:, ci, :3, 3]
        pts = centres[None] @ rot.transpose(1, 2) + trans[:, None, :]  # [B, V, 3]
        uv, z, ok = project_points(pts, intrinsics[:, ci].to(dtype), near=near)
        col = uv[..., 0].floor().long()
        row = uv[..., 1].floor().long()
        ok = ok & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        flat = (row.clamp(0, h - 1) * w + col.clamp(0, w - 1)).view(b, -1)
        d = depth[:, ci].reshape(b, -1).to(dtype).gather(1, flat)
        hit = ok & (d > 0)
        free |= hit & (z < d - margin)
        surface |= hit & ((z - d).abs() <= margin)
    return free & ~surface


def free_space_loss(opacities: torch.Tensor, free: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Mean ``-log(1 - opacity)`` over voxels seen free.

    Args:
        opacities: [B, V] in (0, 1).
        free: [B, V] bool (:func:`free_space_targets`).
        eps: clamp inside the log.

    Returns:
        Scalar; 0 with a graph when no voxel is seen free.
    """
    if free.shape != opacities.shape:
        raise ValueError(
            f"free: expected the opacities' shape {tuple(opacities.shape)}, got {tuple(free.shape)}"
        )
    nll = -torch.log1p(-opacities.clamp(0.0, 1.0 - eps))
    m = free.to(nll.dtype)
    return (nll * m).sum() / m.sum().clamp_min(1.0)
