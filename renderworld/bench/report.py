"""Tables of a bench sweep (``renderworld.bench.sweep``); the pictures: ``renderworld.bench.plots``.

``results.csv`` (one row per point and seed, every column) and ``results.md`` (a table per stage:
mean and spread over the seeds, Δ and ratios against the stage's default point, "no difference"
within the seeds' spread; the ranking check where the preset has one).
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
    "as_float",
    "point_label",
    "ranking_check",
    "ranking_text",
    "result_rows",
    "stage_table",
    "write_csv",
    "write_markdown",
]

CSV_COLUMNS = (
    "stage", "knob", "value", "seed", "phase", "claimed", "is_default", "metric_name", "metric",
    "metric2_name", "metric2", "heldout", "steps", "max_steps", "max_minutes", "train_s",
    "train_wall_s", "train_cpu_s", "eval_s", "infer_ms", "infer_frames", "peak_rss_mib",
    "params", "point_wall_s", "point_cpu_s", "jobs", "grid", "experiment", "fingerprint",
    "reused",
)  # fmt: skip


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


def point_label(row: Mapping[str, Any]) -> str:
    """``default`` or ``knob=value``: how tables and plots name a point."""
    if row["knob"] == DEFAULT:
        return "default"
    return f"{row['knob']}={row['value']}"


def as_float(x: Any) -> float:
    """``float(x)``, NaN when it is not a number (empty CSV cells, None)."""
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
            agg[k] = _mean([as_float(m.get(k)) for m in members])
        agg["spread"] = _range([as_float(m["metric"]) for m in members])
        agg["seeds"] = len(members)
        agg["peak_rss_mib"] = max(as_float(m["peak_rss_mib"]) for m in members)
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
    spread = max(as_float(row.get("spread")), as_float(ref.get("spread")))
    if not math.isnan(spread) and abs(d) <= spread:
        return f"{text} (no difference)"
    return text


def stage_table(rows: Sequence[Mapping[str, Any]], stage: str, phase: str = "") -> str:
    """Markdown table of one stage's budget points (``phase=""``) or ranking points
    (``phase="ranking"``), means over seeds; Δ and ratios are against the default point of the
    same phase; a Δ within the seeds' spread reads "no difference"."""
    spec = STAGE_METRICS[stage]
    mine = [r for r in aggregate(rows) if r["stage"] == stage and r.get("phase", "") == phase]
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
    jobs = sorted({int(as_float(r.get("jobs", 1))) for r in rows if r["stage"] == stage})
    at_once = "/".join(map(str, jobs)) + " point(s) at a time"
    what = f"**{stage}**" + (" ranking points (the main job's step count)" if phase else "")
    lines = [
        f"{what} — budget per point: {budget}; grid of the default point: "
        f"{ref['grid'] if ref else '?'}; seeds per point: {'/'.join(map(str, seeds))} (mean; "
        f'± half the range; a Δ within the larger range of the two points reads "no '
        f'difference"). Measured {at_once}. Inference sample: {spec["sample"]}.'
        + ("" if claim else " **Ranking not claimed**: this budget is below the stable one."),
        "",
        head,
        "|---|" + "---:|" * (cols - 1),
    ]
    for r in mine:
        name = point_label(r)
        if r["knob"] == DEFAULT:
            name = "**default**" + (f" ({r['value']})" if r["value"] else "")
        spread = as_float(r["spread"]) / 2
        lines.append(
            f"| {name} | {_fmt(r['metric'], m1_pct)} | {_fmt(spread, m1_pct)} | "
            f"{_delta(r, ref, m1_pct)} | {_fmt(r['metric2'], m2_pct)} | "
            + (f"{_fmt(r['heldout'], True)} | " if show_held else "")
            + f"{_fmt(r['steps'], False, 0)} | {_fmt(r['train_s'], False, 0)} | "
            f"{_ratio(r['train_s'], ref['train_s']) if ref else '–'} | "
            f"{_fmt(r['infer_ms'], False, 1)} | "
            f"{_ratio(r['infer_ms'], ref['infer_ms']) if ref else '–'} | "
            f"{_fmt(r['peak_rss_mib'], False, 0)} | {int(as_float(r['params'])):,} |"
        )
    return "\n".join(lines)


def ranking_check(rows: Sequence[Mapping[str, Any]], stage: str) -> dict[str, Any] | None:
    """Whether the order of a stage's ranking points at the budget is their order at the
    ranking budget (the main job's step count); None when the stage has no ranking points.

    A pair whose means at the budget differ by no more than the seeds' spread is a tie there
    ("no difference"), so its order may change without contradicting the budget's ranking.

    Returns:
        ``{"budget_order": [str], "full_order": [str], "full_steps": int,
        "contradictions": [(a, b)], "ties": [(a, b)], "holds": bool}``: orders best first,
        each entry the point's label and its mean metric (e.g. ``"default 36.09"``); ``ties``
        are the pairs within the seeds' spread at the budget.
    """
    aggs = [r for r in aggregate(rows) if r["stage"] == stage]
    full = [r for r in aggs if r.get("phase") == RANKING]
    if not full:
        return None

    def key(r):  # the default's value lists the composed knobs, the step count among them
        return r["knob"], "" if r["knob"] == DEFAULT else str(r["value"])

    at_budget = {key(r): r for r in aggs if not r.get("phase")}
    _, higher, m_text = STAGE_METRICS[stage]["metric"]
    scale = 100 if "%" in m_text else 1
    pairs = [(at_budget.get(key(r)), r) for r in full]
    pairs = [(b, f) for b, f in pairs if b is not None]

    def order(items):
        ranked = sorted(items, key=lambda r: r["metric"], reverse=higher)
        return [f"{point_label(r)} {scale * r['metric']:.2f}" for r in ranked]

    contradictions, ties = [], []
    for i, (b1, f1) in enumerate(pairs):
        for b2, f2 in pairs[i + 1 :]:
            d_budget = b1["metric"] - b2["metric"]
            d_full = f1["metric"] - f2["metric"]
            spread = max(as_float(b1["spread"]), as_float(b2["spread"]))
            tie = not math.isnan(spread) and abs(d_budget) <= spread
            if tie:
                ties.append((point_label(b1), point_label(b2)))
            elif d_budget * d_full < 0:
                contradictions.append((point_label(b1), point_label(b2)))
    return {
        "budget_order": order([b for b, _ in pairs]),
        "full_order": order([f for _, f in pairs]),
        "full_steps": int(as_float(full[0]["max_steps"])),
        "contradictions": contradictions,
        "ties": ties,
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
    ties = "; ".join(f"{a} vs {b}" for a, b in chk["ties"])
    return (
        f"Ranking check ({stage}): best first at the budget ({'/'.join(steps)} steps): "
        f"{' > '.join(chk['budget_order'])}; at {chk['full_steps']} steps: "
        f"{' > '.join(chk['full_order'])}. The budget's ranking {verdict}"
        + (f" (order reversed beyond the seeds' spread: {bad})." if bad else ".")
        + (f" No difference at the budget (within the seeds' spread): {ties}." if ties else "")
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
        tables = (stage_table(rows, s), stage_table(rows, s, RANKING), ranking_text(rows, s))
        parts += [p for p in tables if p]
    parts += list(notes)
    path.write_text("\n\n".join(parts) + "\n")
    return path
