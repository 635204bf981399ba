"""Voxel targets back-projected from the 2-D LiDAR label maps (an option, not in the paper).

A label pixel with depth ``d`` and class ``k`` is a 3-D point ``d · K⁻¹ [u, v, 1]`` in its
camera, i.e. a point of the LiDAR sweep it was projected from. Putting those points back
into the voxel grid gives sparse voxel targets without any 3-D label: a voxel holding points
is occupied, with their most frequent class; a voxel the depth maps see through is free
(:func:`free_space_targets`). The loss on them is the "3d" voxel
loss (``occupancy_3d_loss``) restricted to those voxels. Rendering losses compare blended
pixels only, so they leave the per-voxel opacity and class ambiguous (a half-transparent
veil renders almost like a surface); these targets pin them where the 2-D labels say.

Frames and units: camera z in metres (docs/conventions.md#frames), ego frame of the keyframe, voxels
in row-major ``[x, y, z]`` order.
"""

from __future__ import annotations

import math

import torch

from renderworld.constants import FREE_ID, NUM_SEMANTIC_CLASSES, OCC3D_CLASSES
from renderworld.geometry import VoxelGrid, invert_pose, project_points
from renderworld.img2occ.depth_lift import occupancy_3d_loss
from renderworld.img2occ.losses import balanced_class_weights
from renderworld.precision import float32_boundary

__all__ = [
    "STATIC_CLASS_IDS",
    "backproject_labels",
    "backprojected_loss",
    "free_space_targets",
]

#: Classes that do not move between keyframes: adjacent frames' points of these classes
#: land where they are in the keyframe (the ego poses align them); a moving car's would not.
STATIC_CLASS_IDS: tuple[int, ...] = tuple(
    OCC3D_CLASSES.index(n)
    for n in (
        "barrier",
        "traffic_cone",
        "driveable_surface",
        "other_flat",
        "sidewalk",
        "terrain",
        "manmade",
        "vegetation",
    )
)


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


def backproject_labels(
    depth: torch.Tensor,
    semantics: torch.Tensor,
    intrinsics: torch.Tensor,
    cam_to_ego: torch.Tensor,
    grid: VoxelGrid,
    classes=None,
) -> torch.Tensor:
    """Most frequent class of the labelled pixels' 3-D points in each voxel.

    Args:
        depth: [B, C, H, W] LiDAR depth maps, metres camera z (0 = no point).
        semantics: [B, C, H, W] int ids 0..16 (255 or ``FREE_ID`` = no label).
        intrinsics: [B, C, 3, 3] intrinsics of those maps (pixels).
        cam_to_ego: [B, C, 4, 4] camera → (keyframe) ego transforms.
        grid: the voxel grid (ego frame, metres).
        classes: optional iterable of class ids; other labels are ignored.

    Returns:
        [B, V] int64: the class (ties → lower id), ``FREE_ID`` where no point fell.
    """
    b, c, h, w = depth.shape
    if semantics.shape != depth.shape:
        raise ValueError(
            f"semantics: expected the depth maps' shape {tuple(depth.shape)}, got "
            f"{tuple(semantics.shape)}"
        )
    if intrinsics.shape != (b, c, 3, 3) or cam_to_ego.shape != (b, c, 4, 4):
        raise ValueError(
            f"intrinsics/cam_to_ego: expected [{b}, {c}, 3, 3] and [{b}, {c}, 4, 4], got "
            f"{tuple(intrinsics.shape)} and {tuple(cam_to_ego.shape)}"
        )
    n_vox, k = math.prod(grid.shape), NUM_SEMANTIC_CLASSES
    dev, dt = depth.device, torch.float32
    v, u = torch.meshgrid(
        torch.arange(h, dtype=dt, device=dev) + 0.5,
        torch.arange(w, dtype=dt, device=dev) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], 0)  # [3, H, W]
    rays = torch.einsum("bcij,jhw->bcihw", torch.linalg.inv(intrinsics.to(dev, dt)), pix)
    pts = rays * depth.to(dt)[:, :, None]  # [B, C, 3, H, W] camera frame
    pose = cam_to_ego.to(dev, dt)
    pts = torch.einsum("bcij,bcjhw->bchwi", pose[..., :3, :3], pts) + pose[:, :, None, None, :3, 3]
    ijk, inside = grid.points_to_index(pts)  # [B, C, H, W, 3], [B, C, H, W]
    sem = semantics.to(dev).long()
    ok = (depth > 0) & (sem >= 0) & (sem < FREE_ID) & inside
    if classes is not None:
        allowed = torch.zeros(256, dtype=torch.bool, device=dev)
        allowed[torch.as_tensor(list(classes), dtype=torch.long, device=dev)] = True
        ok &= allowed[sem.clamp(0, 255)]
    flat = grid.flat_index(ijk) + (torch.arange(b, device=dev) * n_vox).view(b, 1, 1, 1)
    counts = torch.bincount(flat[ok] * k + sem[ok], minlength=b * n_vox * k).view(b, n_vox, k)
    cls = counts.argmax(-1)  # first maximum: ties go to the lower id
    return torch.where(counts.sum(-1) > 0, cls, torch.full_like(cls, FREE_ID))


@float32_boundary  # float32: LiDAR pixels put back at their depth: geometry
def backprojected_loss(
    opacities: torch.Tensor,
    logits: torch.Tensor,
    centres: torch.Tensor,
    grid,
    batch: dict,
    margin: float,
    near: float,
    adjacent: bool = False,
    eps: float = 1e-6,
    class_balance: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Opacity BCE and class CE against the back-projected voxel targets.

    Args:
        opacities: [B, V] in (0, 1).
        logits: [B, V, K] class logits.
        centres: [V, 3] voxel centres, metres, ego frame.
        grid: a :class:`renderworld.geometry.VoxelGrid`.
        batch: the training batch (keyframe ``depth``, ``semantics``, ``cam_to_ego``,
            ``render_intrinsics``; with ``adjacent`` also the ``adj_*`` views).
        margin: free-space carving margin, metres (voxels seen ``margin`` in front of a
            pixel's depth are free).
        near: voxel centres at camera z <= near are not seen.
        adjacent: add the adjacent keyframes' points of ``STATIC_CLASS_IDS``.
        eps: clamp of the opacities inside the logs.
        class_balance: p in [0, 1]: each target voxel weighs (its class's share of this
            batch's target voxels, free included) ** -p, mean weight 1; 0 = unweighted.

    Returns:
        ``(bce, ce, targets)``: the two scalar losses (0 with a graph when nothing counts)
        and the [B, V] targets (class id, ``FREE_ID`` free, -1 unknown).
    """
    occ = backproject_labels(
        batch["depth"], batch["semantics"], batch["render_intrinsics"], batch["cam_to_ego"], grid
    )
    if adjacent and "adj_depth" in batch:
        adj = backproject_labels(
            batch["adj_depth"], batch["adj_semantics"], batch["adj_render_intrinsics"],
            batch["adj_cam_to_ego"], grid, classes=STATIC_CLASS_IDS,
        )  # fmt: skip
        occ = torch.where(occ == FREE_ID, adj, occ)  # the keyframe's own points win
    free = free_space_targets(
        centres, batch["cam_to_ego"], batch["render_intrinsics"], batch["depth"], margin, near
    )
    hit = occ != FREE_ID
    mask = hit | free
    b = opacities.shape[0]
    weights = None
    if class_balance > 0:
        labels = torch.where(mask, occ, torch.full_like(occ, 255))
        weights = balanced_class_weights(labels, class_balance)[labels.clamp(max=FREE_ID)]
    shape = (b, *grid.shape)
    bce, ce = occupancy_3d_loss(
        opacities, logits, occ.view(shape), mask.view(shape), eps,
        None if weights is None else weights.view(shape),
    )  # fmt: skip
    targets = torch.where(mask, occ, torch.full_like(occ, -1))
    return bce, ce, targets
