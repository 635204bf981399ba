"""Pictures of a bench sweep: ``pareto_<stage>.png`` (metric vs training time and vs inference
ms, default marked, Pareto front drawn) and the planner's latency chart."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from renderworld.bench.knobs import DEFAULT, STAGE_METRICS
from renderworld.bench.report import aggregate, as_float, point_label

__all__ = ["pareto_front", "plot_pareto", "plot_planner"]


def pareto_front(costs: Sequence[float], values: Sequence[float]) -> list[int]:
    """Indices of the non-dominated points (lower cost and higher value are better).

    A point is dominated when another has cost <= and value >= with one of them strict.
    Points with a NaN cost or value are never on the front (and dominate nothing). Equal
    points are all kept.

    Args:
        costs: [N] e.g. training seconds.
        values: [N] e.g. mIoU.

    Returns:
        Indices into the inputs, sorted by cost.

    Raises:
        ValueError: the sequences differ in length.
    """
    if len(costs) != len(values):
        raise ValueError(
            f"costs, values: expected the same length, got {len(costs)} and {len(values)}"
        )
    pts = [
        (float(c), float(v), i)
        for i, (c, v) in enumerate(zip(costs, values, strict=True))
        if not (math.isnan(float(c)) or math.isnan(float(v)))
    ]
    front = []
    for c, v, i in pts:
        dominated = any(c2 <= c and v2 >= v and (c2 < c or v2 > v) for c2, v2, j in pts if j != i)
        if not dominated:
            front.append((c, i))
    return [i for _, i in sorted(front)]


def plot_pareto(rows: Sequence[Mapping[str, Any]], stage: str, path: Path) -> Path | None:
    """Metric vs training s (left) and vs inference ms (right), one marker per point (mean over
    seeds, bar: the seeds' range), the default point a star, the Pareto front drawn.

    The planner trains nothing: its picture is :func:`plot_planner`. A lower-is-better metric
    keeps its axis; the front is of the better direction.

    Returns:
        The PNG path, or None when the stage has no budget points.
    """
    mine = [r for r in aggregate(rows) if r["stage"] == stage and not r.get("phase")]
    if not mine:
        return None
    if stage == "planner":
        return plot_planner(mine, path)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spec = STAGE_METRICS[stage]
    _, higher, m_text = spec["metric"]
    scale = 100 if "%" in m_text else 1
    panels = (("infer_ms", "inference (ms / sample, batch 1)"),)
    if stage != "planner":
        panels = (("train_s", "training time (s)"), *panels)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.9 * len(panels), 3.9), squeeze=False)
    values = [scale * float(r["metric"]) for r in mine]
    errs = [scale * as_float(r["spread"]) / 2 for r in mine]
    errs = [0.0 if math.isnan(e) else e for e in errs]
    for ax, (key, xlabel) in zip(axes[0], panels, strict=True):
        costs = [float(r[key]) for r in mine]
        front = pareto_front(costs, values if higher else [-v for v in values])
        ax.errorbar(costs, values, yerr=errs, fmt="o", color="tab:gray", ms=4, capsize=2,
                    zorder=2)  # fmt: skip
        ax.plot([costs[i] for i in front], [values[i] for i in front], "-o", color="tab:red",
                mfc="none", ms=9, lw=1.5, zorder=3, label="Pareto front")  # fmt: skip
        # Labels alternate above / below in the order of cost, so that near points stay legible.
        above = {
            i: k % 2 == 0 for k, i in enumerate(sorted(range(len(mine)), key=costs.__getitem__))
        }
        for i, r in enumerate(mine):
            if r["knob"] == DEFAULT:
                ax.scatter([costs[i]], [values[i]], marker="*", s=160, color="tab:blue",
                           zorder=4, label="default")  # fmt: skip
            ax.annotate(
                point_label(r), (costs[i], values[i]), fontsize=7,
                xytext=(4, 3 if above[i] else -10),
                textcoords="offset points", fontweight="bold" if r["knob"] == DEFAULT else "normal",
            )  # fmt: skip
        ax.set_xlabel(xlabel)
        ax.set_ylabel(m_text + ("" if higher else ", lower is better"))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    steps = sorted({str(r["max_steps"]) for r in mine})
    seeds = sorted({str(r["seeds"]) for r in mine})
    what = (
        "no training" if stage == "planner" else f"same budget per point ({'/'.join(steps)} steps)"
    )
    claim = "" if all(r.get("claimed", True) for r in mine) else "; ranking not claimed"
    fig.suptitle(f"{stage}: accuracy vs cost, {what}, {'/'.join(seeds)} seed(s){claim}",
                 fontsize=10)  # fmt: skip
    return _save(fig, path)


def plot_planner(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """The planner's points (means over seeds) as bars of latency per plan on a log axis, each
    labelled with its milliseconds and its plan L2 at 3 s (or "latency only" where the point's
    models are untrained), the default in blue.

    Args:
        rows: aggregated planner rows (:func:`renderworld.bench.report.aggregate`).
        path: PNG to write.

    Returns:
        ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted(rows, key=lambda r: as_float(r["infer_ms"]))
    ms = [as_float(r["infer_ms"]) for r in rows]
    fig, ax = plt.subplots(figsize=(7.0, 0.45 * len(rows) + 1.2))
    colors = ["tab:blue" if r["knob"] == DEFAULT else "tab:gray" for r in rows]
    ax.barh(range(len(rows)), ms, color=colors)
    ax.set_xscale("log")
    ax.set_yticks(range(len(rows)), [point_label(r) for r in rows], fontsize=8)
    ax.invert_yaxis()
    for i, r in enumerate(rows):
        l2 = as_float(r["metric"])
        acc = "latency only" if math.isnan(l2) else f"L2 @ 3 s {l2:.2f} m"
        ax.annotate(f"{ms[i]:.1f} ms, {acc}", (ms[i], i), xytext=(4, 0), fontsize=7,
                    textcoords="offset points", va="center")  # fmt: skip
    ax.set_xlim(min(ms) / 2, max(ms) * 30)
    ax.set_xlabel("latency per plan, batch 1 (ms, log scale)")
    ax.grid(alpha=0.3, axis="x")
    fig.suptitle("planner: latency of the main job's planner, one option changed", fontsize=10)
    return _save(fig, path)


def _save(fig: Any, path: Path) -> Path:
    """Lay out, write ``fig`` as a 100-dpi PNG at ``path`` (folders made) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
