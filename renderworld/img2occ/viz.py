"""Pictures: rendered semantics and depth beside the LiDAR-projected targets of one sample."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from renderworld.constants import CAMERA_NAMES, FREE_ID, OCC3D_COLORS
from renderworld.img2occ.losses import IGNORE_LABEL, rendered_distribution

__all__ = ["colorize_semantics", "draw_views"]

_UNLABELLED = (200, 200, 200)  # grey for pixels without a LiDAR label


def colorize_semantics(labels: np.ndarray) -> np.ndarray:
    """[H, W] Occ3D ids (0..17, 255 = no label) → [H, W, 3] uint8 RGB (OCC3D_COLORS)."""
    lut = np.zeros((256, 3), dtype=np.uint8)
    lut[: len(OCC3D_COLORS)] = np.asarray(OCC3D_COLORS, dtype=np.uint8)
    lut[IGNORE_LABEL] = _UNLABELLED
    return lut[np.asarray(labels, dtype=np.int64).clip(0, 255)]


def draw_views(batch: dict, output, path: str | os.PathLike, sample: int = 0) -> Path:
    """Save a PNG: per rendered camera, rendered / target semantics and depth.

    Rendered semantics are the argmax of the rendered class distribution including "ray
    escaped" (drawn as free, white); target pixels without LiDAR are grey.

    Args:
        batch: the batch given to ``model(batch)`` (depth, semantics [B, C, H_r, W_r]).
        output: the model's rendered :class:`~renderworld.img2occ.Img2OccOutput`.
        path: PNG file to write (parent folders created).
        sample: which batch element to draw.

    Returns:
        The written path.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if output.views is None:
        raise ValueError("output: has no rendered views; call model(batch, render=True)")
    b = output.views.alpha.shape[0]
    if not (0 <= sample < b):
        raise ValueError(f"sample: expected 0..{b - 1}, got {sample}")
    views = output.views
    idx = output.view_index[sample].tolist()
    dist = rendered_distribution(views.features[sample], views.alpha[sample]).detach()
    pred_sem = dist.argmax(-1).cpu().numpy()  # index K == FREE_ID: escaped
    pred_depth = views.depth[sample].detach().cpu().numpy()
    tgt_sem = batch["semantics"][sample].cpu().numpy()
    tgt_depth = batch["depth"][sample].cpu().numpy()
    vmax = float(max(tgt_depth.max(), 1.0))
    rows = len(idx)
    fig = Figure(figsize=(13, 2.1 * rows + 0.6), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 4, squeeze=False)
    titles = ("rendered semantics", "LiDAR semantics", "rendered depth", "LiDAR depth")
    for r, ci in enumerate(idx):
        name = CAMERA_NAMES[ci] if ci < len(CAMERA_NAMES) else f"cam {ci}"
        lidar = np.where(tgt_depth[ci] > 0, tgt_depth[ci], np.nan)
        panels = (
            colorize_semantics(np.where(pred_sem[r] == FREE_ID, FREE_ID, pred_sem[r])),
            colorize_semantics(tgt_sem[ci]),
            pred_depth[r],
            lidar,
        )
        for c, (ax, img) in enumerate(zip(axes[r], panels)):
            if c < 2:
                ax.imshow(img, interpolation="nearest")
            else:
                ax.imshow(img, cmap="viridis", vmin=0, vmax=vmax, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(titles[c], fontsize=9)
        axes[r, 0].set_ylabel(name, fontsize=8)
    fig.suptitle(f"Img2Occ sample {sample}: depth colour scale 0..{vmax:.0f} m", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
