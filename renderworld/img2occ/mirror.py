"""The scene mirrored across the ego x-z plane (y -> -y): a batch and the voxel outputs.

Flipping every image (and label map) left-right is what the cameras would see of the world
mirrored across the plane y = 0 of the ego frame. With ``S_e = diag(1, -1, 1)`` (ego y) and
``S_c = diag(-1, 1, 1)`` (camera x):

* a pixel at continuous column ``u`` of a ``W`` wide image moves to ``W - u``, so the
  intrinsics get ``cx -> W - cx`` (and skew ``s -> -s``): ``K'^-1 [W - u, v, 1] = S_c K^-1
  [u, v, 1]``;
* a camera pose becomes ``cam_to_ego' = S_e cam_to_ego S_c`` (a proper rotation again), so
  the back-projected point ``S_e X_ego`` is the mirror image of ``X_ego``;
* voxel grids symmetric in y (``range_min.y == -range_max.y``, as the Occ3D range is) flip
  their y axis: voxel ``(i, j, k)`` holds what voxel ``(i, Y - 1 - j, k)`` held.

Used for mirrored-scene training augmentation and the mirrored second readout pass
(``Img2OccConfig.mirror_prob`` / ``mirror_readout``).
"""

from __future__ import annotations

import torch

from renderworld.constants import GridSpec

__all__ = ["average_with_mirror", "check_mirror_grid", "mirror_batch", "mirror_voxels"]

# Keys of an Img2OccDataset batch and how each one mirrors.
_IMAGE_KEYS = ("images", "depth", "semantics", "adj_depth", "adj_semantics")
_POSE_KEYS = ("cam_to_ego", "adj_cam_to_ego")
# intrinsics key -> key whose last dimension is that camera's width
_INTRINSICS_KEYS = {
    "intrinsics": "images",
    "render_intrinsics": "depth",
    "adj_render_intrinsics": "adj_depth",
}
_GRID_KEYS = ("occ", "mask_camera", "mask_lidar")
_PASS_KEYS = ("meta",)


def check_mirror_grid(grid: GridSpec, tol: float = 1e-6) -> None:
    """Raise ValueError unless ``grid`` is symmetric about y = 0 (its voxels mirror onto voxels)."""
    lo, hi = float(grid.range_min[1]), float(grid.range_max[1])
    if abs(lo + hi) > tol:
        raise ValueError(
            f"grid {grid.name!r}: mirroring needs a y range symmetric about 0, got [{lo}, {hi}]"
        )


def _mirror_intrinsics(k: torch.Tensor, width: int) -> torch.Tensor:
    out = k.clone()
    out[..., 0, 2] = width - k[..., 0, 2]
    out[..., 0, 1] = -k[..., 0, 1]
    return out


def _mirror_pose(t: torch.Tensor) -> torch.Tensor:
    s_ego = torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=t.dtype, device=t.device)
    s_cam = torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=t.dtype, device=t.device)
    return s_ego[:, None] * t * s_cam[None, :]  # diag(s_ego) @ t @ diag(s_cam)


def mirror_batch(batch: dict) -> dict:
    """The batch of the mirrored scene (a new dict; the input is left unchanged).

    Args:
        batch: Img2OccDataset items stacked on B (module docstring of
            :mod:`renderworld.data.datasets`): images [B, C, 3, H, W], depth / semantics
            [B, C, H_r, W_r], intrinsics [B, C, 3, 3], cam_to_ego [B, C, 4, 4], optional
            ``adj_*`` views and ``occ`` / masks [B, X, Y, Z] on a y-symmetric grid.

    Returns:
        The same keys: image-like maps flipped along W, intrinsics and poses as in the module
        docstring, voxel grids flipped along Y, ``meta`` shared.

    Raises:
        ValueError: a key this function does not know how to mirror (nothing is dropped
            silently), or intrinsics without the maps that give their image width.
    """
    known = (*_IMAGE_KEYS, *_POSE_KEYS, *_INTRINSICS_KEYS, *_GRID_KEYS, *_PASS_KEYS)
    unknown = sorted(k for k in batch if k not in known)
    if unknown:
        raise ValueError(f"mirror_batch: no mirroring rule for batch key(s) {unknown}")
    out = {}
    for key, value in batch.items():
        if key in _IMAGE_KEYS:
            out[key] = value.flip(-1)
        elif key in _POSE_KEYS:
            out[key] = _mirror_pose(value)
        elif key in _INTRINSICS_KEYS:
            source = _INTRINSICS_KEYS[key]
            if source not in batch:
                raise ValueError(f"mirror_batch: {key!r} needs {source!r} for the image width")
            out[key] = _mirror_intrinsics(value, int(batch[source].shape[-1]))
        elif key in _GRID_KEYS:
            if value.ndim != 4:
                raise ValueError(f"{key}: expected [B, X, Y, Z], got {tuple(value.shape)}")
            out[key] = value.flip(2)
        else:
            out[key] = value
    return out


def mirror_voxels(x: torch.Tensor, grid_shape: tuple[int, int, int]) -> torch.Tensor:
    """Per-voxel values of the mirrored scene back on the original grid (flip along Y).

    Args:
        x: [B, V, ...] with V = X·Y·Z in row-major [x, y, z] order.
        grid_shape: (X, Y, Z).

    Returns:
        [B, V, ...], voxel ``(i, j, k)`` taking the value of ``(i, Y - 1 - j, k)``.
    """
    b, rest = x.shape[0], x.shape[2:]
    return x.view(b, *grid_shape, *rest).flip(2).reshape(b, -1, *rest)


@torch.no_grad()
def average_with_mirror(gaussians, mirrored, grid_shape: tuple[int, int, int]) -> None:
    """Readout of a scene and its mirror image: mean opacity and mean class distribution.

    Args:
        gaussians: :class:`~renderworld.img2occ.head.AnchorGaussians` of the scene; its
            ``opacities`` [B, V] and ``logits`` [B, V, K] are replaced (in place) by the
            averages, ``logits`` by the log of the mean class probabilities.
        mirrored: the Gaussians predicted for :func:`mirror_batch` of the same batch.
        grid_shape: (X, Y, Z), V = X·Y·Z.

    The Gaussians' means, scales and rotations stay the scene's own: the readout uses only
    opacities and classes.
    """
    op = mirror_voxels(mirrored.opacities, grid_shape)
    probs = mirror_voxels(mirrored.logits, grid_shape).softmax(-1)
    gaussians.opacities = 0.5 * (gaussians.opacities + op)
    mean = 0.5 * (gaussians.logits.softmax(-1) + probs)
    gaussians.logits = mean.clamp_min(1e-12).log()
