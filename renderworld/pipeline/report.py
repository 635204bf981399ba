"""The main job's report: metric tables and pictures gathered from the pipeline's outputs.

``write_report(out_dir, sections)`` writes ``<out_dir>/report.md`` and its pictures under
``<out_dir>/figures/``. Pictures: training curves from each run's ``metrics.csv`` and bird's-eye
views of occupancy (the top-most non-free class of each column, Occ3D colours).
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from pathlib import Path

from renderworld.constants import FREE_ID, OCC3D_CLASSES
from renderworld.training.figures import bev_image

__all__ = [
    "UnreadableFile",
    "bev_image",
    "load_json",
    "metrics_table",
    "per_class_table",
    "plot_training_curves",
    "unreadable_note",
    "write_report",
]


def plot_training_curves(metrics_csv: Path, out_png: Path, keys=("train/loss",)) -> Path | None:
    """Plot chosen keys of a run's long-format ``metrics.csv`` (step, epoch, key, value).

    One panel per key (exact metric names, e.g. ``val/model/miou_avg``); a key the file does not
    hold gets no panel (never an empty one). None when the file is missing or holds none.
    """
    if not Path(metrics_csv).is_file():
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series: dict[str, list[tuple[float, float]]] = defaultdict(list)
    with open(metrics_csv) as fh:
        for row in csv.DictReader(fh):
            if row["key"] in keys:
                series[row["key"]].append((float(row["step"]), float(row["value"])))
    shown = [k for k in keys if series.get(k)]
    if not shown:
        return None
    fig, axes = plt.subplots(1, len(shown), figsize=(4.2 * len(shown), 3), squeeze=False)
    for ax, key in zip(axes[0], shown, strict=True):
        xs, ys = zip(*series[key], strict=True)
        ax.plot(xs, ys, marker="o" if len(xs) < 12 else None)
        ax.set_title(key)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=90)
    plt.close(fig)
    return out_png


def metrics_table(metrics: dict, rows: list[tuple[str, str]], digits: int = 2) -> str:
    """A two-column markdown table of chosen metrics (fractions shown as percentages)."""
    lines = ["| metric | value |", "|---|---|"]
    for label, key in rows:
        value = metrics.get(key)
        text = "n/a" if value is None or value != value else f"{100 * value:.{digits}f} %"
        lines.append(f"| {label} | {text} |")
    return "\n".join(lines)


def per_class_table(metrics: dict, prefix: str) -> str:
    """Per-class IoU (classes 0..16) as a one-row markdown table."""
    names = OCC3D_CLASSES[:FREE_ID]
    head = "| " + " | ".join(names) + " |"
    sep = "|" + "---|" * len(names)
    vals = []
    for n in names:
        v = metrics.get(f"{prefix}iou_{n}")
        vals.append("–" if v is None or v != v else f"{100 * v:.1f}")
    return "\n".join([head, sep, "| " + " | ".join(vals) + " |"])


class UnreadableFile(ValueError):
    """A report input that exists but cannot be read.

    Attributes:
        path: the file.
        reason: what went wrong (the parser's message).
    """

    def __init__(self, path: Path, reason: str) -> None:
        super().__init__(f"{path}: unreadable ({reason})")
        self.path, self.reason = Path(path), reason


def load_json(path: Path) -> dict:
    """A JSON object file's content, or {} when the file does not exist (its step has not run).

    Raises:
        UnreadableFile: the file exists but is not a readable JSON object (a torn write, a
            disk error): the report says so instead of dropping the section.
    """
    path = Path(path)
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:  # UnicodeDecodeError and JSONDecodeError included
        raise UnreadableFile(path, f"{type(err).__name__}: {err}") from None
    if not isinstance(data, dict):
        raise UnreadableFile(path, f"expected a JSON object, got a {type(data).__name__}")
    return data


def unreadable_note(err: UnreadableFile) -> str:
    """The report's line for an input it could not read (in place of what it would show)."""
    return (
        f"**Not shown: `{err.path}` is unreadable** ({err.reason}). Re-run the step that writes it."
    )


def write_report(out_dir: Path, sections: list[tuple[str, str]]) -> Path:
    """Write ``report.md`` from ``(title, markdown body)`` sections."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    text = ["# RenderWorld — main job report", ""]
    for title, body in sections:
        text += [f"## {title}", "", body.strip(), ""]
    path = out_dir / "report.md"
    path.write_text("\n".join(text))
    return path
