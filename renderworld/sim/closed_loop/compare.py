"""Paired comparison of two closed-loop runs (``closed_loop.csv`` of ``tools/drive.py``).

Two runs of the same scenes (a knob on and off, two bundles, two planners) differ scene by
scene; one collision moves the mean PDMS of 16 scenes by about 0.05. The comparison pairs the
rows by scene and reads each run's planner row (by default the same planner in both), so that
the mean difference comes with its standard error over the scenes (the spread of the paired
differences: a knob whose difference is within about two of them has not shown anything), how
many scenes went up and down, per behaviour, and the scenes that moved most.
``tools/compare_drives.py`` prints it.

A side may hold several runs of the same scenes (:func:`average_runs`: e.g. the bundles of
several trainings of one recipe): its scores are then each scene's mean over its runs, and
:func:`run_spread` lists each run's own mean, since two trainings of one world-model recipe
drive a set of scenes as far apart as many a change does (``docs/protocol.md``).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

__all__ = [
    "PAIR_KEYS",
    "average_runs",
    "compare_runs",
    "comparison_markdown",
    "event_count",
    "load_run",
    "run_spread",
    "spread_markdown",
]

#: Scores compared, and the event counts beside them (scenes where it happened).
PAIR_KEYS = ("PDMS", "EP", "TTC", "C", "NC", "DAC")
_EVENTS = ("at_fault_collision", "off_road")
_NEEDED = ("scene", "behaviour", "planner", *PAIR_KEYS, *_EVENTS)


def load_run(path, planner: str, name: str = "a") -> pd.DataFrame:
    """The rows of ``planner`` in a run: ``closed_loop.csv`` or the directory holding it.

    Raises:
        FileNotFoundError: naming ``name`` and the path when there is no such file.
        ValueError: naming ``name`` when a column is missing, the planner has no row (listing
            the planners there are) or a scene appears twice.
    """
    path = Path(path)
    csv = path / "closed_loop.csv" if path.is_dir() else path
    if not csv.is_file():
        raise FileNotFoundError(f"{name}: no closed_loop.csv at {csv}")
    df = pd.read_csv(csv)
    missing = [c for c in _NEEDED if c not in df.columns]
    if missing:
        raise ValueError(f"{name}: {csv} lacks columns {missing} (not a tools/drive.py table?)")
    rows = df[df["planner"] == planner]
    if rows.empty:
        raise ValueError(
            f"{name}: no rows of planner {planner!r} in {csv} (planners: "
            f"{sorted(df['planner'].unique())})"
        )
    if rows["scene"].duplicated().any():
        raise ValueError(f"{name}: planner {planner!r} drove a scene twice in {csv}")
    out = rows.set_index("scene")
    out.attrs["worlds"] = _worlds(csv.parent / "closed_loop.json")
    return out


def average_runs(runs: list[pd.DataFrame], name: str = "a") -> pd.DataFrame:
    """One side's rows from several runs of the same scenes (:func:`load_run` each): every
    score of :data:`PAIR_KEYS` and each event (then the fraction of runs it happened in) is the
    scene's mean over the runs. One run is returned as it is.

    Raises:
        ValueError: naming ``name`` when there is no run, the runs drove other worlds or
            other scenes, or a scene's behaviour differs between them.
    """
    if not runs:
        raise ValueError(f"{name}: no run given")
    if len(runs) == 1:
        return runs[0]
    first = runs[0]
    for k, run in enumerate(runs[1:], start=2):
        if run.attrs.get("worlds") != first.attrs.get("worlds"):
            raise ValueError(f"{name}: run {k} drove other worlds than run 1")
        if set(run.index) != set(first.index):
            odd = sorted(set(run.index) ^ set(first.index))
            raise ValueError(f"{name}: run {k} and run 1 drove other scenes ({odd[:3]} ...)")
        if (run.loc[first.index, "behaviour"] != first["behaviour"]).any():
            raise ValueError(f"{name}: run {k} gives a scene another behaviour than run 1")
    keys = [*PAIR_KEYS, *_EVENTS]
    stacked = pd.concat([r.loc[first.index, keys].astype(float) for r in runs])
    out = stacked.groupby(level=0, sort=False).mean().loc[first.index]
    out.insert(0, "behaviour", first["behaviour"])
    out.attrs["worlds"] = first.attrs.get("worlds")
    out.attrs["runs"] = len(runs)
    return out


def run_spread(runs: list[pd.DataFrame], scenes=None) -> list[dict]:
    """Each run's mean PDMS and its scenes with an at-fault collision, over ``scenes`` (default
    each run's own): how far apart the runs of one side lie."""
    out = []
    for run in runs:
        rows = run if scenes is None else run.loc[list(scenes)]
        out.append({"PDMS": float(rows["PDMS"].mean()),
                    "at_fault": int(rows["at_fault_collision"].astype(bool).sum())})  # fmt: skip
    return out


def _worlds(path: Path) -> dict | None:
    """The preset and seed a run's worlds were built from (its ``closed_loop.json``
    settings), or None where the file or the settings are missing."""
    import json

    try:
        settings = json.loads(path.read_text()).get("settings", {})
    except (OSError, ValueError):
        return None
    if "preset" not in settings:
        return None
    return {"preset": settings["preset"], "seed": settings.get("seed")}


def compare_runs(a: pd.DataFrame, b: pd.DataFrame, top: int = 5) -> dict:
    """Pair two runs' rows (:func:`load_run`) on their common scenes.

    Args:
        a, b: the rows of one planner in each run, indexed by scene.
        top: how many of the scenes that moved most to list.

    Returns:
        ``{"scenes": n, "only_a": [...], "only_b": [...], "overall": {...}, "behaviours":
        {behaviour: {...}}, "moved": [(scene, behaviour, PDMS a, PDMS b), ...]}``; each
        summary holds ``n``, the means ``<key>_a`` / ``<key>_b`` of every score of
        :data:`PAIR_KEYS`, ``PDMS_se`` (the standard error of the mean paired PDMS difference;
        NaN for one scene), ``up`` / ``down`` (scenes whose PDMS rose or fell by more than
        1e-6) and the scenes with an at-fault collision and off the road in each run.

    Raises:
        ValueError: when the runs drove worlds of another preset or seed (read from each run's
            ``closed_loop.json`` where there is one: the dev interactions' scene-6000 is not
            the interaction split's), share no scene, or a shared scene's behaviour differs.
    """
    wa, wb = a.attrs.get("worlds"), b.attrs.get("worlds")
    if wa and wb and wa != wb:
        raise ValueError(
            f"a, b: the runs drove different worlds (a: {wa}, b: {wb}): a scene name of one is "
            "another scene in the other"
        )
    common = [s for s in a.index if s in b.index]
    if not common:
        raise ValueError("a, b: the runs share no scene (different presets or seeds?)")
    pa, pb = a.loc[common], b.loc[common]
    clash = [s for s in common if pa.at[s, "behaviour"] != pb.at[s, "behaviour"]]
    if clash:
        raise ValueError(f"a, b: scenes {clash[:3]} have different behaviours in the two runs")

    def summary(idx) -> dict:
        out = {"n": len(idx)}
        for k in PAIR_KEYS:
            out[f"{k}_a"] = float(pa.loc[idx, k].mean())
            out[f"{k}_b"] = float(pb.loc[idx, k].mean())
        d = pb.loc[idx, "PDMS"] - pa.loc[idx, "PDMS"]
        out["PDMS_se"] = float(d.std(ddof=1) / len(d) ** 0.5) if len(d) > 1 else float("nan")
        out["up"], out["down"] = int((d > 1e-6).sum()), int((d < -1e-6).sum())
        for k in _EVENTS:  # scenes; on a side of several runs the mean count per run
            out[f"{k}_a"] = event_count(pa.loc[idx, k])
            out[f"{k}_b"] = event_count(pb.loc[idx, k])
        return out

    behaviours = {}
    for beh in dict.fromkeys(pa["behaviour"]):
        behaviours[beh] = summary([s for s in common if pa.at[s, "behaviour"] == beh])
    d = (pb["PDMS"] - pa["PDMS"]).abs().sort_values(ascending=False, kind="stable")
    moved = [
        (s, pa.at[s, "behaviour"], float(pa.at[s, "PDMS"]), float(pb.at[s, "PDMS"]))
        for s in d.index[:top]
        if d[s] > 1e-6
    ]
    return {
        "scenes": len(common),
        "only_a": [s for s in a.index if s not in b.index],
        "only_b": [s for s in b.index if s not in a.index],
        "overall": summary(common),
        "behaviours": behaviours,
        "moved": moved,
    }


def event_count(col: pd.Series) -> int | float:
    """Scenes where an event happened: an int for one run's column of flags, the sum of the
    fractions of runs (a float) for an averaged side."""
    if col.dtype == bool or col.dtype == object:
        return int(col.astype(bool).sum())
    return float(col.sum())


def _fmt(x) -> str:
    return str(x) if isinstance(x, int) else f"{x:.2f}"


def _se(se: float) -> str:
    return "" if se != se else f" ± {se:.3f}"  # NaN (one scene): none


def comparison_markdown(cmp: dict, label_a: str = "a", label_b: str = "b") -> str:
    """Tables of :func:`compare_runs`: overall and per behaviour, then the scenes that moved."""
    head = (
        f"| scenes | n | PDMS {label_a} | PDMS {label_b} | b − a ± s.e. | up / down | EP a → b | "
        "TTC a → b | C a → b | at fault a → b | off road a → b |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|"
    )

    def row(name, s):
        return (
            f"| {name} | {s['n']} | {s['PDMS_a']:.3f} | {s['PDMS_b']:.3f} | "
            f"{s['PDMS_b'] - s['PDMS_a']:+.3f}{_se(s['PDMS_se'])} | {s['up']} / {s['down']} | "
            f"{s['EP_a']:.3f} → {s['EP_b']:.3f} | {s['TTC_a']:.3f} → {s['TTC_b']:.3f} | "
            f"{s['C_a']:.3f} → {s['C_b']:.3f} | "
            f"{_fmt(s['at_fault_collision_a'])} → {_fmt(s['at_fault_collision_b'])} | "
            f"{_fmt(s['off_road_a'])} → {_fmt(s['off_road_b'])} |"
        )

    lines = [head, row("all", cmp["overall"])]
    lines += [row(b, s) for b, s in cmp["behaviours"].items()]
    if cmp["moved"]:
        lines += ["", f"Scenes that moved most (PDMS {label_a} → {label_b}):", ""]
        lines += [f"- {s} ({beh}): {x:.3f} → {y:.3f}" for s, beh, x, y in cmp["moved"]]
    for key, label in (("only_a", label_a), ("only_b", label_b)):
        if cmp[key]:
            lines.append(f"\nOnly in {label} (not compared): {', '.join(cmp[key])}")
    return "\n".join(lines)


def spread_markdown(spreads: dict[str, list[dict]]) -> str:
    """Lines naming each side's runs (:func:`run_spread`) where a side holds more than one, and
    the widest gap between two runs of one side; empty where every side is one run."""
    if all(len(v) < 2 for v in spreads.values()):
        return ""
    parts, gap = [], 0.0
    for label, runs in spreads.items():
        pdms = [r["PDMS"] for r in runs]
        gap = max(gap, max(pdms) - min(pdms))
        means = " / ".join(f"{p:.3f}" for p in pdms)
        faults = " / ".join(str(r["at_fault"]) for r in runs)
        plural = "s" if len(runs) > 1 else ""
        parts.append(f"{label}: {len(runs)} run{plural}, PDMS {means} (at fault {faults})")
    return (
        "; ".join(parts)
        + f". The runs of one side lie up to {gap:.3f} apart: a difference between the sides "
        "below that has not shown anything (each side's scores are its runs' mean per scene)."
    )
