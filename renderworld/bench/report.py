"""Tables and Pareto plots of a bench sweep (``renderworld.bench.sweep``).

``results.csv`` (one row per point and seed, every column), ``results.md`` (a table per stage:
mean and spread over the seeds, Δ and ratios against the stage's default point, "no difference"
within the seeds' spread; the ranking check where the preset has one) and ``pareto_<stage>.png``
(metric vs training time and vs inference ms, default marked, Pareto front drawn).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from renderworld.bench.knobs import DEFAULT, STAGE_METRICS, format_value
from renderworld.bench.sweep import RANKING

__all__ = [
    "aggregate",
    "ranking_check",
    "ranking_text",
    "pareto_front",
    "result_rows",
    "stage_table",
    "write_csv",
    "write_markdown",
    "plot_pareto",
    "write_outputs",
]

CSV_COLUMNS = (
    "stage", "knob", "value", "seed", "phase", "claimed", "is_default", "metric_name", "metric",
    "metric2_name", "metric2", "heldout", "steps", "max_steps", "max_minutes", "train_s",
    "train_wall_s", "train_cpu_s", "eval_s", "infer_ms", "infer_frames", "peak_rss_mib",
    "params", "point_wall_s", "point_cpu_s", "jobs", "grid", "experiment", "fingerprint",
    "reused",
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
        held = spec.get("heldout")
        row.update(
            seed=r.get("seed", 0),
            phase=r.get("phase", ""),
            claimed=r.get("claimed", True),
            jobs=r.get("jobs", 1),
            heldout=metrics.get(held[0], float("nan")) if held else float("nan"),
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


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _mean(xs: Sequence[float]) -> float:
    xs = [x for x in xs if not math.isnan(x)]
    return sum(xs) / len(xs) if xs else float("nan")


def _range(xs: Sequence[float]) -> float:
    xs = [x for x in xs if not math.isnan(x)]
    return max(xs) - min(xs) if len(xs) > 1 else float("nan")


def aggregate(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (stage, phase, knob, value) over its seeds, in first-seen order.

    Each aggregate holds the first row's fields, then ``metric`` / ``metric2`` / ``heldout`` /
    ``train_s`` / ``infer_ms`` as means over the seeds, ``spread`` = max - min of the metric over
    the seeds (NaN with one seed), ``seeds`` (how many) and ``peak_rss_mib`` the largest.
    """
    groups: dict[tuple, list[Mapping[str, Any]]] = {}
    for r in rows:
        key = (r["stage"], r.get("phase", ""), r["knob"], str(r["value"]))
        groups.setdefault(key, []).append(r)
    out = []
    for members in groups.values():
        agg = dict(members[0])
        for k in ("metric", "metric2", "heldout", "train_s", "infer_ms", "steps"):
            agg[k] = _mean([_num(m.get(k)) for m in members])
        agg["spread"] = _range([_num(m["metric"]) for m in members])
        agg["seeds"] = len(members)
        agg["peak_rss_mib"] = max(_num(m["peak_rss_mib"]) for m in members)
        out.append(agg)
    return out


def _delta(row: Mapping[str, Any], ref: Mapping[str, Any] | None, pct: bool) -> str:
    """Δ of the mean metric vs the default's; "no difference" within the seeds' spread."""
    if ref is None or math.isnan(row["metric"]) or math.isnan(ref["metric"]):
        return "–"
    d = row["metric"] - ref["metric"]
    if row is ref:
        return "+0.00"
    text = f"{100 * d:+.2f}" if pct else f"{d:+.2f}"
    spread = max(_num(row.get("spread")), _num(ref.get("spread")))
    if not math.isnan(spread) and abs(d) <= spread:
        return f"{text} (no difference)"
    return text


def stage_table(rows: Sequence[Mapping[str, Any]], stage: str) -> str:
    """Markdown table of one stage's budget points (means over seeds); Δ and ratios are against
    its default point; a Δ within the seeds' spread reads "no difference"."""
    spec = STAGE_METRICS[stage]
    mine = [r for r in aggregate(rows) if r["stage"] == stage and not r.get("phase")]
    if not mine:
        return ""
    mine.sort(key=lambda r: r["knob"] != DEFAULT)  # stable: the default point first
    ref = next((r for r in mine if r["knob"] == DEFAULT), None)
    _, _, m1_text = spec["metric"]
    m1_pct = "%" in m1_text
    m2_name, _, m2_text = spec["metric2"]
    m2_pct = "%" in m2_text
    held = spec.get("heldout")
    show_held = held is not None and any(not math.isnan(r["heldout"]) for r in mine)
    steps = {(r["max_steps"], r["max_minutes"]) for r in mine}
    budget = "; ".join(f"{s} steps, capped at {m} min" for s, m in sorted(steps, key=str))
    if stage == "planner":
        budget = "no training (latency of the main job's planner)"
    seeds = sorted({r["seeds"] for r in mine})
    claim = all(r.get("claimed", True) for r in mine)
    head = (
        f"| point | {m1_text} | ± spread | Δ vs default | {m2_text} | "
        + (f"{held[1]} | " if show_held else "")
        + "steps | train s | × default | infer ms | × default | peak RSS MiB | params |"
    )
    cols = head.count("|") - 1
    jobs = sorted({int(_num(r.get("jobs", 1))) for r in rows if r["stage"] == stage})
    at_once = "/".join(map(str, jobs)) + " point(s) at a time"
    lines = [
        f"**{stage}** — budget per point: {budget}; grid of the default point: "
        f"{ref['grid'] if ref else '?'}; seeds per point: {'/'.join(map(str, seeds))} (mean; "
        f'± half the range; a Δ within the larger range of the two points reads "no '
        f'difference"). Measured {at_once}. Inference sample: {spec["sample"]}.'
        + ("" if claim else " **Ranking not claimed**: this budget is below the stable one."),
        "",
        head,
        "|---|" + "---:|" * (cols - 1),
    ]
    for r in mine:
        name = _label(r)
        if r["knob"] == DEFAULT:
            name = "**default**" + (f" ({r['value']})" if r["value"] else "")
        spread = _num(r["spread"]) / 2
        lines.append(
            f"| {name} | {_fmt(r['metric'], m1_pct)} | {_fmt(spread, m1_pct)} | "
            f"{_delta(r, ref, m1_pct)} | {_fmt(r['metric2'], m2_pct)} | "
            + (f"{_fmt(r['heldout'], True)} | " if show_held else "")
            + f"{_fmt(r['steps'], False, 0)} | {_fmt(r['train_s'], False, 0)} | "
            f"{_ratio(r['train_s'], ref['train_s']) if ref else '–'} | "
            f"{_fmt(r['infer_ms'], False, 1)} | "
            f"{_ratio(r['infer_ms'], ref['infer_ms']) if ref else '–'} | "
            f"{_fmt(r['peak_rss_mib'], False, 0)} | {int(_num(r['params'])):,} |"
        )
    return "\n".join(lines)


def ranking_check(rows: Sequence[Mapping[str, Any]], stage: str) -> dict[str, Any] | None:
    """Whether the order of a stage's ranking points at the budget is their order at the
    ranking budget (the main job's step count); None when the stage has no ranking points.

    A pair whose means at the budget differ by no more than the seeds' spread is a tie there
    ("no difference"), so its order may change without contradicting the budget's ranking.

    Returns:
        ``{"budget_order": [labels], "full_order": [labels], "full_steps": int,
        "contradictions": [(a, b)], "holds": bool}`` (orders best first).
    """
    aggs = [r for r in aggregate(rows) if r["stage"] == stage]
    full = [r for r in aggs if r.get("phase") == RANKING]
    if not full:
        return None
    at_budget = {(r["knob"], str(r["value"])): r for r in aggs if not r.get("phase")}
    higher = STAGE_METRICS[stage]["metric"][1]
    pairs = [(at_budget.get((r["knob"], str(r["value"]))), r) for r in full]
    pairs = [(b, f) for b, f in pairs if b is not None]

    def order(items):
        ranked = sorted(items, key=lambda r: r["metric"], reverse=higher)
        return [_label(r) for r in ranked]

    contradictions = []
    for i, (b1, f1) in enumerate(pairs):
        for b2, f2 in pairs[i + 1 :]:
            d_budget = b1["metric"] - b2["metric"]
            d_full = f1["metric"] - f2["metric"]
            spread = max(_num(b1["spread"]), _num(b2["spread"]))
            tie = not math.isnan(spread) and abs(d_budget) <= spread
            if not tie and d_budget * d_full < 0:
                contradictions.append((_label(b1), _label(b2)))
    return {
        "budget_order": order([b for b, _ in pairs]),
        "full_order": order([f for _, f in pairs]),
        "full_steps": int(_num(full[0]["max_steps"])),
        "contradictions": contradictions,
        "holds": not contradictions,
    }


def ranking_text(rows: Sequence[Mapping[str, Any]], stage: str) -> str:
    """One markdown paragraph of :func:`ranking_check` ("" without ranking points)."""
    chk = ranking_check(rows, stage)
    if chk is None:
        return ""
    steps = sorted(
        {str(r["max_steps"]) for r in rows if r["stage"] == stage and not r.get("phase")}
    )
    verdict = "**holds**" if chk["holds"] else "**does not hold**"
    bad = "; ".join(f"{a} vs {b}" for a, b in chk["contradictions"])
    return (
        f"Ranking check ({stage}): best first at the budget ({'/'.join(steps)} steps): "
        f"{' > '.join(chk['budget_order'])}; at {chk['full_steps']} steps: "
        f"{' > '.join(chk['full_order'])}. The budget's ranking {verdict}"
        + (f" (order reversed beyond the seeds' spread: {bad})." if bad else ".")
    )


def write_markdown(
    rows: Sequence[Mapping[str, Any]], path: Path, title: str = "", notes: Sequence[str] = ()
) -> Path:
    """Write one table per stage (in the rows' stage order) and ``notes`` to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stages = list(dict.fromkeys(r["stage"] for r in rows))
    parts = [f"# {title}"] if title else []
    for s in stages:
        parts += [p for p in (stage_table(rows, s), ranking_text(rows, s)) if p]
    parts += list(notes)
    path.write_text("\n\n".join(parts) + "\n")
    return path


def plot_pareto(rows: Sequence[Mapping[str, Any]], stage: str, path: Path) -> Path | None:
    """Metric vs training s (left) and vs inference ms (right), one marker per point (mean over
    seeds, bar: the seeds' range), the default point a star, the Pareto front drawn.

    The planner trains nothing: one panel, metric vs inference ms. A lower-is-better metric
    (the planner's L2) keeps its axis; the front is of the better direction.

    Returns:
        The PNG path, or None when the stage has no budget points.
    """
    mine = [r for r in aggregate(rows) if r["stage"] == stage and not r.get("phase")]
    if not mine:
        return None
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
    errs = [scale * _num(r["spread"]) / 2 for r in mine]
    errs = [0.0 if math.isnan(e) else e for e in errs]
    for ax, (key, xlabel) in zip(axes[0], panels, strict=True):
        costs = [float(r[key]) for r in mine]
        front = pareto_front(costs, values if higher else [-v for v in values])
        ax.errorbar(costs, values, yerr=errs, fmt="o", color="tab:gray", ms=4, capsize=2,
                    zorder=2)  # fmt: skip
        ax.plot([costs[i] for i in front], [values[i] for i in front], "-", color="tab:red",
                lw=1.5, zorder=3, label="Pareto front")  # fmt: skip
        for i, r in enumerate(mine):
            if r["knob"] == DEFAULT:
                ax.scatter([costs[i]], [values[i]], marker="*", s=160, color="tab:blue",
                           zorder=4, label="default")  # fmt: skip
            ax.annotate(  # labels alternate above / below so that near points stay legible
                _label(r), (costs[i], values[i]), fontsize=7, xytext=(4, 3 if i % 2 else -10),
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
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_outputs(
    results: Sequence[Mapping[str, Any]], out: Path, title: str = "", notes: Sequence[str] = ()
) -> dict[str, Path]:
    """``results.csv``, ``results.md`` and one ``pareto_<stage>.png`` per stage under ``out``."""
    rows = result_rows(results)
    out = Path(out)
    paths = {"csv": write_csv(rows, out / "results.csv")}
    paths["md"] = write_markdown(rows, out / "results.md", title, notes)
    for stage in dict.fromkeys(r["stage"] for r in rows):
        png = plot_pareto(rows, stage, out / f"pareto_{stage}.png")
        if png is not None:
            paths[f"pareto_{stage}"] = png
    return paths
