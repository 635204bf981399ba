"""Tables and Pareto plots of a bench sweep (``renderworld.bench.sweep``).

``results.csv`` (one row per point, every column), ``results.md`` (a table per stage with ratios
against the stage's default point) and ``pareto_<stage>.png`` (metric vs training time and vs
inference ms, Pareto front highlighted, points labelled).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from renderworld.bench.sweep import DEFAULT, STAGE_METRICS, format_value

__all__ = [
    "pareto_front",
    "result_rows",
    "stage_table",
    "write_csv",
    "write_markdown",
    "plot_pareto",
    "write_outputs",
]

CSV_COLUMNS = (
    "stage", "knob", "value", "is_default", "metric_name", "metric", "metric2_name", "metric2",
    "steps", "max_steps", "max_minutes", "train_s", "train_wall_s", "eval_s", "infer_ms",
    "infer_frames", "peak_rss_mib", "params", "grid", "experiment", "fingerprint", "reused",
)  # fmt: skip


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


def result_rows(results: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Flatten point results into table rows (``CSV_COLUMNS``), metrics as stored (fractions)."""
    rows = []
    for r in results:
        spec = STAGE_METRICS[r["stage"]]
        (m1, _, _), (m2, _, _) = spec["metric"], spec["metric2"]
        metrics = r.get("metrics", {})
        if r["knob"] == DEFAULT:
            # The default point's value column: the stage's knobs as composed, for the table.
            value = ", ".join(f"{k}={v}" for k, v in (r.get("knob_values") or {}).items())
        else:
            value = r.get("knob_value") or format_value(r["value"])
        row = {k: r.get(k, "") for k in CSV_COLUMNS}
        row.update(
            value=value,
            is_default=r["knob"] == DEFAULT,
            metric_name=m1,
            metric=metrics.get(m1, float("nan")),
            metric2_name=m2,
            metric2=metrics.get(m2, float("nan")),
        )
        rows.append(row)
    return rows


def write_csv(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Write ``rows`` (from :func:`result_rows`) to ``path`` with ``CSV_COLUMNS``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return path


def _ratio(x: float, ref: float) -> str:
    if any(math.isnan(float(v)) for v in (x, ref)) or ref == 0:
        return "–"
    return f"{x / ref:.2f}×"


def _fmt(x: Any, pct: bool, digits: int = 2) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    if math.isnan(x):
        return "–"
    return f"{100 * x:.{digits}f}" if pct else f"{x:.{digits}f}"


def _label(row: Mapping[str, Any]) -> str:
    if row["knob"] == DEFAULT:
        return "default"
    return f"{row['knob']}={row['value']}"


def stage_table(rows: Sequence[Mapping[str, Any]], stage: str) -> str:
    """Markdown table of one stage's rows; ratios are against its default point."""
    spec = STAGE_METRICS[stage]
    mine = [r for r in rows if r["stage"] == stage]
    if not mine:
        return ""
    mine.sort(key=lambda r: r["knob"] != DEFAULT)  # stable: the default point first
    ref = next((r for r in mine if r["knob"] == DEFAULT), None)
    m2_name, _, m2_text = spec["metric2"]
    m2_pct = "%" in m2_text
    steps = {(r["max_steps"], r["max_minutes"]) for r in mine}
    budget = "; ".join(f"{s} steps, capped at {m} min" for s, m in sorted(steps, key=str))
    head = (
        f"| point | {spec['metric'][2]} | Δ vs default | {m2_text} | steps | train s | "
        f"× default | infer ms | × default | peak RSS MiB | params |"
    )
    lines = [
        f"**{stage}** — budget per point: {budget}; grid of the default point: "
        f"{ref['grid'] if ref else '?'}. Inference sample: {spec['sample']}.",
        "",
        head,
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in mine:
        delta = "–"
        if ref is not None and not math.isnan(float(r["metric"])):
            delta = f"{100 * (float(r['metric']) - float(ref['metric'])):+.2f}"
        name = _label(r)
        if r["knob"] == DEFAULT:
            name = "**default**" + (f" ({r['value']})" if r["value"] else "")
        lines.append(
            f"| {name} | {_fmt(r['metric'], True)} | {delta} | "
            f"{_fmt(r['metric2'], m2_pct)} | {r['steps']} | {_fmt(r['train_s'], False, 0)} | "
            f"{_ratio(float(r['train_s']), float(ref['train_s'])) if ref else '–'} | "
            f"{_fmt(r['infer_ms'], False, 1)} | "
            f"{_ratio(float(r['infer_ms']), float(ref['infer_ms'])) if ref else '–'} | "
            f"{_fmt(r['peak_rss_mib'], False, 0)} | {int(r['params']):,} |"
        )
    return "\n".join(lines)


def write_markdown(rows: Sequence[Mapping[str, Any]], path: Path, title: str = "") -> Path:
    """Write one table per stage (in the rows' stage order) to ``path``; return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stages = list(dict.fromkeys(r["stage"] for r in rows))
    parts = [f"# {title}"] if title else []
    parts += [stage_table(rows, s) for s in stages]
    path.write_text("\n\n".join(parts) + "\n")
    return path


def plot_pareto(rows: Sequence[Mapping[str, Any]], stage: str, path: Path) -> Path | None:
    """Metric vs training s (left) and vs inference ms (right), Pareto front highlighted.

    Returns:
        The PNG path, or None when the stage has no rows.
    """
    mine = [r for r in rows if r["stage"] == stage]
    if not mine:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spec = STAGE_METRICS[stage]
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.8))
    values = [100 * float(r["metric"]) for r in mine]
    for ax, key, xlabel in zip(
        axes, ("train_s", "infer_ms"), ("training time (s)", "inference (ms / sample)"), strict=True
    ):
        costs = [float(r[key]) for r in mine]
        front = pareto_front(costs, values)
        ax.scatter(costs, values, c="tab:gray", s=22, zorder=2)
        fx = [costs[i] for i in front]
        fy = [values[i] for i in front]
        ax.plot(fx, fy, "-o", color="tab:red", ms=6, zorder=3, label="Pareto front")
        for i, r in enumerate(mine):
            weight = "bold" if r["knob"] == DEFAULT else "normal"
            ax.annotate(
                _label(r), (costs[i], values[i]), fontsize=7, xytext=(4, 3),
                textcoords="offset points", fontweight=weight,
            )  # fmt: skip
        ax.set_xlabel(xlabel)
        ax.set_ylabel(spec["metric"][2])
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    steps = sorted({str(r["max_steps"]) for r in mine})
    fig.suptitle(
        f"{stage}: accuracy vs cost, same budget per point ({'/'.join(steps)} steps); "
        "red: Pareto front",
        fontsize=10,
    )
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


def write_outputs(
    results: Sequence[Mapping[str, Any]], out: Path, title: str = ""
) -> dict[str, Path]:
    """``results.csv``, ``results.md`` and one ``pareto_<stage>.png`` per stage under ``out``."""
    rows = result_rows(results)
    out = Path(out)
    paths = {"csv": write_csv(rows, out / "results.csv")}
    paths["md"] = write_markdown(rows, out / "results.md", title)
    for stage in dict.fromkeys(r["stage"] for r in rows):
        png = plot_pareto(rows, stage, out / f"pareto_{stage}.png")
        if png is not None:
            paths[f"pareto_{stage}"] = png
    return paths
