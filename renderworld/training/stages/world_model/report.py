"""The ``world_model`` evaluation table: one table, model and baselines, one or two settings.

Rows are (setting, method): the "3D-Occ" setting (GT occupancy inputs, GT targets) and the
"Camera" setting (Img2Occ pseudo-label inputs, GT targets), each with the model and the
baselines computed on that setting's inputs. A setting's metrics are ``<prefix><method>/<name>``
(optionally ``val/``-prefixed); the prefix is ``""`` for the run's own setting and ``"camera/"``
for the Camera setting added by ``tools/eval.py ... pseudo_labels=DIR``.

Printed table and markdown show the headline conventions (mIoU / IoU full volume, L2 at horizon,
collision vs GT boxes at horizon); the CSV holds these and the others (camera-mask mIoU / IoU,
mean-to-horizon L2, collision vs GT occupancy, the collisions' hit / evaluated counts, skipped-GT
and outside-grid counts, mIoU / IoU /
L2 of the straight and the turning windows, per-class IoU at each horizon). A value that
does not apply to a method (a baseline without a planner, a planner without a forecast) is "–"
in the text and markdown, explained by a legend line under the table, and empty in the CSV.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

from renderworld.constants import FREE_ID, OCC3D_CLASSES
from renderworld.metrics import PlanningMetric

__all__ = [
    "CHECKED",
    "CHECKED_HISTORY_COMMAND",
    "HISTORY_COMMAND",
    "MODEL_MOVERS",
    "METHODS",
    "REPORT_BASENAME",
    "REFERENCES",
    "SETTING_LABELS",
    "SPLITS",
    "NOT_APPLICABLE",
    "collision_counts_table",
    "report_tables",
    "write_report",
]

#: The model given the command derived from the history instead of the GT future.
HISTORY_COMMAND = "model_history_command"
#: The model's plan checked against its own forecast (renderworld.planning.checked), with the
#: GT-derived command and with the command from the history.
CHECKED, CHECKED_HISTORY_COMMAND = "model_checked", "model_checked_history_command"
#: The current frame with the model's learned movers moved, warped along the GT future poses.
MODEL_MOVERS = "warp_gt_model_movers"
#: (metric prefix, table label, has an occupancy forecast, has a trajectory)
METHODS: tuple[tuple[str, str, bool, bool], ...] = (
    ("model", "model", True, True),
    (HISTORY_COMMAND, "model, command from history", True, True),
    (CHECKED, "model, checked plan", False, True),
    (CHECKED_HISTORY_COMMAND, "model, checked plan, command from history", False, True),
    ("model_warp", "model, warp only", True, False),
    ("model_net", "model, tokens only", True, False),
    ("copy_paste", "Copy&Paste", True, False),
    ("warp_cv", "CV-warp", True, False),
    ("warp_ctr", "CTR-warp", True, False),
    ("warp_object_cv", "object-CV warp", True, False),
    ("cv_traj", "CV-trajectory", False, True),
    ("ctr_traj", "CTR-trajectory", False, True),
    ("warp_gt_pose", "GT-pose warp (ref.)", True, False),
    ("warp_gt_object_cv", "GT-pose + object-CV movers (ref.)", True, False),
    (MODEL_MOVERS, "GT-pose + model movers (ref.)", True, False),
    ("warp_gt_movers", "GT-pose warp + GT movers (ref.)", True, False),
)
#: Methods that read the future (reported as references, never as competitors).
REFERENCES = ("warp_gt_pose", "warp_gt_object_cv", MODEL_MOVERS, "warp_gt_movers")
#: Window subsets of the CSV's split columns (see ``splits.TURN_THRESHOLD_DEG``).
SPLITS = ("straight", "turning")
REPORT_BASENAME = "world_model_eval"
#: Table label of each setting.
SETTING_LABELS = {"occ3d": "3D-Occ", "camera": "Camera"}
#: How a value that does not apply is shown (text and markdown).
NOT_APPLICABLE = "–"
_LEGEND_NA = (
    f"{NOT_APPLICABLE}: not applicable — Copy&Paste and the warps forecast occupancy but plan no "
    "trajectory (no L2 / collision); the CV / CTR trajectories plan but forecast no occupancy "
    "(no mIoU / IoU)."
)
_LEGEND_BASELINES = (
    "CV = constant velocity (last displacement repeated, heading fixed); CTR = constant turn "
    "rate (last displacement and last heading change repeated); both read the history only. "
    "GT-pose warp (ref.) = the current frame warped along the ground-truth future poses "
    "(x, y, yaw): it reads the future, an upper bound for a static world, not a method. "
    "object-CV warp = the current frame along the CTR poses, each movable bird's-eye-view "
    "component shifted by its own velocity measured against frame t-2 (history only). "
    "GT-pose + object-CV movers (ref.) = the current frame with its movers moved as in the "
    "object-CV warp, warped along the ground-truth future poses: the pose-warp model's design "
    "with perfect ego poses; reads the future, not a method. GT-pose + model movers (ref.) = "
    "the same with the movers moved by the model's learned mover head: its movers alone. "
    "GT-pose warp + GT movers (ref.) = the GT-pose warp without the current movers, the "
    "ground-truth future movers pasted in: reads the future, an upper bound, not a method. "
    "Movers = mIoU of the eight movable classes (car, truck, bus, trailer, "
    "construction_vehicle, pedestrian, bicycle, motorcycle), from the same confusion as the "
    "mIoU. Head = heading error of the plan, degrees (median / mean over windows)."
)
_LEGEND_COMMAND = (
    "The model reads a driving command (left / right / straight) derived from the ground-truth "
    "future: the lateral offset of the 3 s position, ±2 m (as VAD / UniAD), so the model row "
    "reads the future through its command; the baselines read none. model, command from "
    "history = the same model given the command that rule derives from the constant-turn-rate "
    "extrapolation of the history: no input reads the future."
)
_LEGEND_VARIANTS = (
    "model, warp only = the current frame warped along the model's predicted poses; model, "
    "tokens only = the token network's decoded forecast; model = the warp where its source "
    "lies on the current grid, the tokens elsewhere. model, checked plan = the best of the "
    "candidates around the model's plan scored against its own forecast (collisions with the "
    "forecast movers and obstacles, drivable area, progress, time to collision, comfort; "
    "renderworld.planning.checked), the trajectory a planner bundle drives with check=True."
)
_LEGEND_NAN = (
    "nan: undefined — no class present in GT or forecast at that horizon, or no window with a "
    "valid future frame there."
)


def _hname(h: float) -> str:
    return f"{h:g}s"


def _columns(horizons_s: tuple[float, ...]) -> list[tuple[str, str, float]]:
    """(header, metric suffix, scale) of the printed table."""
    hs = [_hname(h) for h in horizons_s] + ["avg"]
    cols = []
    for label, metric, scale in (
        ("mIoU", "miou", 100.0),
        ("Movers", "movers_miou", 100.0),
        ("IoU", "iou", 100.0),
        ("L2", "l2_at_horizon", 1.0),
        ("Head med", "heading_median", 1.0),
        ("Head mean", "heading_mean", 1.0),
        ("Col", "collision_boxes_at_horizon", 100.0),
    ):
        hz = hs[:-1] if metric.startswith("heading") else hs
        cols += [(f"{label} {h}", f"{metric}_{h}", scale) for h in hz]
    return cols


def _csv_columns(horizons_s: tuple[float, ...]) -> list[tuple[str, str, float]]:
    """(csv column, metric suffix, scale): the table's columns plus the other conventions."""
    hs = [_hname(h) for h in horizons_s] + ["avg"]
    out = []
    for metric, unit, scale in (
        ("miou", "pct", 100.0),
        ("movers_miou", "pct", 100.0),
        ("iou", "pct", 100.0),
        ("cam/miou", "pct", 100.0),
        ("cam/movers_miou", "pct", 100.0),
        ("cam/iou", "pct", 100.0),
        ("l2_at_horizon", "m", 1.0),
        ("l2_mean_to_horizon", "m", 1.0),
        ("collision_boxes_at_horizon", "pct", 100.0),
        ("collision_boxes_mean_to_horizon", "pct", 100.0),
        ("collision_occupancy_at_horizon", "pct", 100.0),
        ("collision_occupancy_mean_to_horizon", "pct", 100.0),
    ):
        for h in hs:
            out.append((f"{metric.replace('/', '_')}_{h}_{unit}", f"{metric}_{h}", scale))
    for metric in ("heading_median", "heading_mean"):
        out += [(f"{metric}_{h}_deg", f"{metric}_{h}", 1.0) for h in hs[:-1]]
    for src in PlanningMetric.SOURCES:
        for what in ("gt_skipped", "outside_grid"):
            out.append((f"collision_{src}_{what}", f"collision_{src}_{what}", 1.0))
        for conv in _CONVENTIONS:
            for what in ("hits", "evaluated"):
                for h in hs[:-1]:
                    name = f"collision_{src}_{what}_{conv}_{h}"
                    out.append((name, name, 1.0))
    for split in SPLITS:
        out.append((f"{split}_windows", f"{split}/num_windows", 1.0))
        for metric, unit, scale in (("miou", "pct", 100.0), ("iou", "pct", 100.0),
                                    ("l2_at_horizon", "m", 1.0)):  # fmt: skip
            for h in hs:
                out.append((f"{split}_{metric}_{h}_{unit}", f"{split}/{metric}_{h}", scale))
    for c in OCC3D_CLASSES[:FREE_ID]:
        for h in hs[:-1]:
            out.append((f"iou_{c}_{h}_pct", f"class_iou/{c}_{h}", 100.0))
    return out


_CONVENTIONS = ("at_horizon", "mean_to_horizon")


def collision_counts_table(
    metrics: Mapping[str, float],
    horizons_s: tuple[float, ...],
    settings: Sequence[tuple[str, str]] = (("3D-Occ", ""),),
) -> str:
    """Markdown table of the collision counts behind the rates: colliding / evaluated waypoints
    per planner, source (GT boxes, GT object occupancy) and convention; "" when the metrics
    hold no counts (an older metrics file)."""
    hs = [_hname(h) for h in horizons_s]
    rows = []
    for label, prefix in settings:
        for method, name, _, plans in METHODS:
            if not plans:
                continue
            for src in PlanningMetric.SOURCES:
                for conv in _CONVENTIONS:
                    cells = []
                    for h in hs:
                        hit = _value(
                            metrics, f"{prefix}{method}", f"collision_{src}_hits_{conv}_{h}", 1
                        )
                        n = _value(
                            metrics, f"{prefix}{method}", f"collision_{src}_evaluated_{conv}_{h}", 1
                        )
                        if hit is None or n is None:
                            break
                        rate = f" ({100 * hit / n:.1f} %)" if n else ""
                        cells.append(f"{int(hit)} / {int(n)}{rate}")
                    if len(cells) == len(hs):
                        what = conv.replace("_", " ")
                        rows.append(
                            f"| {label} | {name} | {src} | {what} | " + " | ".join(cells) + " |"
                        )
    if not rows:
        return ""
    head = "| setting | planner | vs GT | convention | " + " | ".join(hs) + " |"
    return "\n".join([head, "|---|---|---|---|" + "---:|" * len(hs), *rows]) + "\n"


def _value(metrics: Mapping[str, float], prefix: str, suffix: str, scale: float) -> float | None:
    key = f"{prefix}/{suffix}"
    for k in (key, f"val/{key}"):
        if k in metrics:
            return float(metrics[k]) * scale
    return None


def _fmt(v: float | None) -> str:
    if v is None:
        return NOT_APPLICABLE
    if math.isnan(v):
        return "nan"
    return f"{v:.2f}"


def _check_settings(settings: Sequence[tuple[str, str]]) -> None:
    if not settings:
        raise ValueError("settings: expected at least one (label, metric prefix) pair, got none")
    for s in settings:
        if not (isinstance(s, tuple) and len(s) == 2 and all(isinstance(x, str) for x in s)):
            raise ValueError(f"settings: expected (label, metric prefix) string pairs, got {s!r}")


def report_tables(
    metrics: Mapping[str, float],
    horizons_s: tuple[float, ...],
    header: list[str],
    settings: Sequence[tuple[str, str]] = (("3D-Occ", ""),),
) -> tuple[str, str, str]:
    """The evaluation table as (plain text, markdown, CSV).

    Args:
        metrics: the stage's metrics (``<prefix><method>/<name>``, optionally ``val/``-prefixed).
        horizons_s: the reported horizons.
        header: description lines (split, protocol) printed above the table.
        settings: (table label, metric prefix) per setting, in row order.

    Returns:
        Text and markdown with a legend under the table for every "–" / "nan" shown; CSV with
        columns ``setting, method, <metric>_<h>_<unit>...`` (not applicable: empty).
    """
    _check_settings(settings)
    cols = _columns(horizons_s)
    rows = []  # (setting label, method label, table values, csv values)
    csv_cols = _csv_columns(horizons_s)
    for label, prefix in settings:
        for method, name, _, _ in METHODS:
            key = f"{prefix}{method}"
            vals = [_value(metrics, key, c[1], c[2]) for c in cols]
            if all(v is None for v in vals):
                continue  # a method this evaluation did not run (e.g. an older metrics file)
            rows.append((label, name, vals, [_value(metrics, key, c[1], c[2]) for c in csv_cols]))
    shown = [v for r in rows for v in r[2]]
    legend = [_LEGEND_BASELINES]
    if any(r[1] == "model" for r in rows):
        legend.append(_LEGEND_COMMAND)
    if any(r[1] == "model, warp only" for r in rows):
        legend.append(_LEGEND_VARIANTS)
    if any(v is None for v in shown):
        legend.append(_LEGEND_NA)
    if any(v is not None and math.isnan(v) for v in shown):
        legend.append(_LEGEND_NAN)

    width = max(9, *(len(c[0]) + 1 for c in cols))
    mw = max(len(m[1]) for m in METHODS) + 1
    lines = [f"# {h}" for h in header]
    lines.append(f"{'setting':<9}{'method':<{mw}}" + "".join(f"{c[0]:>{width}}" for c in cols))
    md = [*(f"> {h}  " for h in header), ""]
    md.append("| setting | method | " + " | ".join(c[0] for c in cols) + " |")
    md.append("|---|---|" + "---:|" * len(cols))
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["setting", "method", *(c[0] for c in csv_cols)])
    for label, name, vals, csv_vals in rows:
        lines.append(f"{label:<9}{name:<{mw}}" + "".join(f"{_fmt(v):>{width}}" for v in vals))
        md.append(f"| {label} | {name} | " + " | ".join(_fmt(v) for v in vals) + " |")
        writer.writerow([label, name, *("" if v is None else repr(v) for v in csv_vals)])
    lines += [f"# {x}" for x in legend]
    md += ["", *(f"{x}  " for x in legend)] if legend else []
    return "\n".join(lines), "\n".join(md) + "\n", buf.getvalue()


def write_report(
    metrics: Mapping[str, float],
    run_dir: str | Path,
    horizons_s: tuple[float, ...],
    header: list[str],
    settings: Sequence[tuple[str, str]] = (("3D-Occ", ""),),
    extra_md: str = "",
) -> str:
    """Write ``world_model_eval.csv`` and ``.md`` into ``run_dir``; return the text table.

    ``extra_md`` (e.g. the motion tables) is appended to the markdown."""
    text, md, csv_text = report_tables(metrics, horizons_s, header, settings)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    counts = collision_counts_table(metrics, horizons_s, settings)
    if counts:
        md += (
            "\nCollisions: colliding / evaluated waypoints (rate). At horizon: the waypoint at "
            "the horizon's step; mean to horizon: every step up to it. Steps where the GT "
            "trajectory itself collides are skipped (CSV: `collision_<source>_gt_skipped`).\n\n"
            + counts
        )
    (run_dir / f"{REPORT_BASENAME}.md").write_text(md + extra_md)
    (run_dir / f"{REPORT_BASENAME}.csv").write_text(csv_text)
    return text
