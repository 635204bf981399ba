"""Pictures of world-model evaluations: BEV occupancy over time, planned trajectories over BEV.

Both functions take plain arrays (no model, no dataset) and write a small PNG (Agg backend).
Bird's-eye views follow :func:`bev_image`: driving direction (+x)
up, +y (left) on the left; axes in metres of the ego frame; Occ3D colours with a legend of the
classes shown.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from renderworld.constants import (
    EGO_LENGTH,
    EGO_WIDTH,
    FREE_ID,
    OCC3D_CLASSES,
    OCC3D_COLORS,
    GridSpec,
)

__all__ = ["bev_image", "bev_forecast_figure", "trajectory_figure"]

_DPI = 80


def bev_image(occ: np.ndarray) -> np.ndarray:
    """Bird's-eye view of occupancy: colour of the highest non-free voxel per (x, y) column.

    Args:
        occ: [X, Y, Z] uint8 Occ3D ids, ego frame (x forward, y left).

    Returns:
        [Y, X, 3] uint8 RGB image with x up and y to the left (as seen from above, driving up).
    """
    occ = np.asarray(occ)
    if occ.ndim != 3:
        raise ValueError(f"occ: expected [X, Y, Z], got shape {occ.shape}")
    occupied = occ != FREE_ID
    z_top = occ.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)
    top = np.take_along_axis(occ, z_top[..., None], axis=2)[..., 0]
    top = np.where(occupied.any(axis=2), top, FREE_ID)
    rgb = np.asarray(OCC3D_COLORS, dtype=np.uint8)[top]  # [X, Y, 3]
    return rgb[::-1, ::-1].copy()  # rows: x from front (top) to back; columns: y left to right


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _check_frame(frame, grid: GridSpec, name: str) -> np.ndarray:
    arr = np.asarray(frame)
    if arr.shape != tuple(grid.shape):
        raise ValueError(
            f"{name}: expected occupancy of shape {tuple(grid.shape)}, got {arr.shape}"
        )
    if arr.dtype != np.uint8:
        raise ValueError(f"{name}: expected uint8 Occ3D class ids, got dtype {arr.dtype}")
    if arr.size and int(arr.max()) > FREE_ID:
        raise ValueError(f"{name}: class ids must be 0..{FREE_ID}, got max {int(arr.max())}")
    return arr


def _extent(grid: GridSpec) -> tuple[float, float, float, float]:
    """imshow extent of a bev_image: (left, right, bottom, top) = (y max, y min, x min, x max)."""
    (x0, y0, _), (x1, y1, _) = grid.range_min, grid.range_max
    return (y1, y0, x0, x1)


def _legend(fig, classes: set[int], ncol: int) -> None:
    from matplotlib.patches import Patch

    handles = [  # free too: white, next to manmade's near-white
        Patch(
            facecolor=np.asarray(OCC3D_COLORS[c]) / 255.0,
            edgecolor="0.4",
            linewidth=0.5,
            label=OCC3D_CLASSES[c] if c != FREE_ID else "free (empty column)",
        )
        for c in sorted(classes)
    ]
    if handles:
        fig.legend(handles=handles, loc="lower center", ncol=ncol, fontsize=7, frameon=False)


def bev_forecast_figure(
    rows: Sequence[tuple[str, Sequence[np.ndarray]]],
    col_titles: Sequence[str],
    grid: GridSpec,
    out_png: str | Path,
    title: str | None = None,
    marks: Sequence[tuple[float, float]] = (),
) -> Path:
    """A grid of bird's-eye views: one row per source, one column per time.

    Args:
        rows: (row label, frames) per row; each frame uint8 [X, Y, Z] Occ3D ids on ``grid``.
        col_titles: one title per column (e.g. ``"t = 0"``, ``"+1 s"``).
        grid: the voxel grid of every frame (gives the axes in metres).
        out_png: file to write (folders are created).
        title: optional figure title.
        marks: (x, y) points, metres in the ego frame of the first column's frames, circled
            in that column of every row (e.g. an object the figure is about).

    Returns:
        ``out_png`` as a Path.

    Raises:
        ValueError: no rows or columns, a row whose frame count differs from ``col_titles``,
            a frame of the wrong shape, dtype or class range, or a mark that is not a finite
            (x, y) pair.
    """
    rows, col_titles = list(rows), list(col_titles)
    if not rows or not col_titles:
        raise ValueError(
            f"rows/col_titles: expected at least one row and one column, got {len(rows)} rows "
            f"and {len(col_titles)} columns"
        )
    frames = []
    for r, (label, row) in enumerate(rows):
        row = list(row)
        if len(row) != len(col_titles):
            raise ValueError(
                f"rows[{r}] ({label!r}): expected {len(col_titles)} frames (one per column), "
                f"got {len(row)}"
            )
        frames.append([_check_frame(f, grid, f"rows[{r}][{c}]") for c, f in enumerate(row)])
    marks = np.asarray(list(marks), dtype=np.float64) if len(marks) else None
    if marks is not None and (
        marks.ndim != 2 or marks.shape[1] != 2 or not np.isfinite(marks).all()
    ):
        raise ValueError(f"marks: expected finite (x, y) pairs, got {marks.tolist()}")
    plt = _plt()
    nr, nc = len(rows), len(col_titles)
    fig, axes = plt.subplots(nr, nc, figsize=(1.75 * nc + 0.9, 1.75 * nr + 0.9), squeeze=False)
    present: set[int] = set()
    for r, (label, _) in enumerate(rows):
        for c in range(nc):
            ax, occ = axes[r][c], frames[r][c]
            present |= set(np.unique(occ).tolist())
            ax.imshow(bev_image(occ), extent=_extent(grid), interpolation="nearest")
            if c == 0 and marks is not None:  # ring around each mark (plot axes: y, x)
                lims = ax.get_xlim(), ax.get_ylim()
                ax.scatter(marks[:, 1], marks[:, 0], s=420, facecolors="none",
                           edgecolors="black", linewidths=0.9)  # fmt: skip
                ax.set_xlim(lims[0])
                ax.set_ylim(lims[1])
            ax.tick_params(labelsize=6)
            if r == 0:
                ax.set_title(col_titles[c], fontsize=8)
            if c == 0:
                ax.set_ylabel(f"{label}\nx (m)", fontsize=7)
            else:
                ax.set_yticklabels([])
            if r == nr - 1:
                ax.set_xlabel("y (m)", fontsize=7)
            else:
                ax.set_xticklabels([])
    if title:
        fig.suptitle(title, fontsize=9)
    _legend(fig, present, ncol=6)
    fig.tight_layout(rect=(0, 0.07 + 0.02 * (len(present) > 12), 1, 1))
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=_DPI)
    plt.close(fig)
    return out


_STYLES = {  # label -> (colour, marker, line style)
    "GT future": ("black", "o", "-"),
    "model": ("tab:red", "^", "-"),
    "CV baseline": ("tab:blue", "s", "--"),
}


def _ego_box(ax) -> None:
    hl, hw = EGO_LENGTH / 2, EGO_WIDTH / 2
    xs = [-hl, hl, hl, -hl, -hl]
    ys = [-hw, -hw, hw, hw, -hw]
    ax.plot(ys, xs, color="magenta", linewidth=1.2, label="ego box")


def trajectory_figure(
    panels: Sequence[Mapping],
    grid: GridSpec,
    out_png: str | Path,
    view: tuple[float, float, float, float] | None = None,
    title: str | None = None,
) -> Path:
    """Planned vs GT trajectories over the current frame's bird's-eye view, one panel each.

    Args:
        panels: dicts with ``occ`` uint8 [X, Y, Z] (the current frame, ego frame),
            ``trajectories`` {label: float [S, 2] (x, y) metres, current ego frame} and an
            optional ``title``. Labels "GT future", "model", "CV baseline" get fixed styles.
        grid: the grid of ``occ``.
        out_png: file to write.
        view: shown (x min, x max, y min, y max) in metres, ego frame; default the grid's.
        title: optional figure title.

    Returns:
        ``out_png`` as a Path.

    Raises:
        ValueError: no panels, a panel without ``occ`` / ``trajectories``, a trajectory that
            is not a finite [S, 2] array, or an occupancy of the wrong shape.
    """
    panels = list(panels)
    if not panels:
        raise ValueError("panels: expected at least one panel, got none")
    if view is not None and (len(view) != 4 or not (view[0] < view[1] and view[2] < view[3])):
        raise ValueError(f"view: expected (x min, x max, y min, y max) with min < max, got {view}")
    for i, p in enumerate(panels):
        if not isinstance(p, Mapping) or "occ" not in p or "trajectories" not in p:
            raise ValueError(f"panels[{i}]: expected a mapping with 'occ' and 'trajectories'")
        _check_frame(p["occ"], grid, f"panels[{i}].occ")
        for name, t in p["trajectories"].items():
            t = np.asarray(t, dtype=np.float64)
            if t.ndim != 2 or t.shape[1] != 2 or not np.isfinite(t).all():
                raise ValueError(
                    f"panels[{i}].trajectories[{name!r}]: expected a finite [S, 2] array, got "
                    f"shape {t.shape}"
                )
    plt = _plt()
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(3.0 * n, 4.0), squeeze=False)
    for ax, p in zip(axes[0], panels, strict=True):
        occ = np.asarray(p["occ"])
        ax.imshow(bev_image(occ), extent=_extent(grid), interpolation="nearest", alpha=0.55)
        for name, t in p["trajectories"].items():
            t = np.asarray(t, dtype=np.float64)
            color, marker, ls = _STYLES.get(name, (None, ".", "-"))
            xs, ys = np.r_[0.0, t[:, 0]], np.r_[0.0, t[:, 1]]
            ax.plot(ys, xs, ls, color=color, marker=marker, markersize=3, linewidth=1.2,
                    label=name)  # fmt: skip
        _ego_box(ax)
        if view is not None:
            ax.set_xlim(view[3], view[2])  # +y (left) on the left
            ax.set_ylim(view[0], view[1])
        ax.set_xlabel("y (m, left +)", fontsize=7)
        ax.set_ylabel("x (m, forward)", fontsize=7)
        ax.tick_params(labelsize=6)
        if p.get("title"):
            ax.set_title(str(p["title"]), fontsize=8)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper right", fontsize=7, ncol=len(labels), frameon=False)
    if title:
        fig.suptitle(title, fontsize=9, x=0.02, ha="left")
    fig.tight_layout(rect=(0, 0, 1, 0.92))
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=_DPI)
    plt.close(fig)
    return out
