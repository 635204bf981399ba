"""Paired comparison of two closed-loop runs (``closed_loop.csv`` of ``tools/drive.py``).

Two runs of the same scenes (a knob on and off, two bundles, two planners) differ scene by
scene; one collision moves the mean PDMS of 16 scenes by about 0.05. The comparison pairs the
rows by scene and reads each run's planner row (by default the same planner in both), so that
the mean difference comes with its standard error over the scenes (the spread of the paired
differences: a knob whose difference is within about two of them has not shown anything), how
many scenes went up and down, per behaviour, and the scenes that moved most.
``tools/compare_drives.py`` prints it.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

__all__ = ["load_run", "compare_runs", "comparison_markdown", "PAIR_KEYS"]

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
        for k in _EVENTS:
            out[f"{k}_a"] = int(pa.loc[idx, k].astype(bool).sum())
            out[f"{k}_b"] = int(pb.loc[idx, k].astype(bool).sum())
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
            f"{s['at_fault_collision_a']} → {s['at_fault_collision_b']} | "
            f"{s['off_road_a']} → {s['off_road_b']} |"
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
