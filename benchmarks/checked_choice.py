"""Why a checked plan departs from the learned one in open loop: the choice, window by window.

Evaluates a world-model checkpoint with ``tools/eval.py``'s code (the GT-command row) and
records, for every window's checked plan (:func:`renderworld.planning.checked.check_plan`):
the chosen candidate's kind and offset, the learned plan's own candidate (the first: the plan,
held back by IDM behind a leader where it closes in) and its sub-scores, and the L2 at 3 s to
the ground truth of the raw plan, of the plan's candidate and of the chosen one. Prints:

* per chosen kind: windows, mean L2 at 3 s of the raw and of the checked plan;
* where the learned plan lost: which of its sub-scores failed (NC, DAC, TTC, C, EP < 0.8);
* where it won but was held back: how much the hold-back cost in L2;
* where the checked plan meets a ground-truth box at 3 s (the evaluation's collision count):
  which candidate was driven, and whether the raw plan met one too;
* the ground-truth future scored by the same check, as one more candidate of each window (it
  takes no part in the choice): how often the check would refuse what the logged car did, and
  which sub-score refused it (the comfort quantity named) — the check's false alarms.
* per scene behaviour (simulated scenes) and for the scenes that add the most L2: windows, the
  raw and the checked plan's mean L2 at 3 s, the L2 the check adds there (metres, summed over
  the windows) and the GT-box contacts at 3 s of both.

Score development splits with it, not test splits. ``--check KNOB=VALUE`` sets
:class:`~renderworld.planning.candidates.CheckConfig` knobs (as ``tools/eval.py check=``).

Usage::

    python benchmarks/checked_choice.py --data-root data/sim_dev --split all \\
        --tokenizer outputs/demo/tokenizer/checkpoints/last.pt \\
        --world-model outputs/demo/world_model/checkpoints/last.pt --out outputs/checked_choice
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import renderworld.planning.checked as checked_mod  # noqa: E402
import renderworld.training.stages.world_model.pose_warp as wmp  # noqa: E402
from benchmarks.dev_eval import add_eval_args, check_files, evaluate_world_model  # noqa: E402
from renderworld.constants import KEYFRAME_DT  # noqa: E402
from renderworld.metrics import collisions_with_boxes  # noqa: E402
from renderworld.planning.candidates import Candidates  # noqa: E402
from renderworld.sim.scene import behaviour_of  # noqa: E402

SUBSCORES = ("NC", "DAC", "EP", "TTC", "C", "score")


def window_record(result, raw: np.ndarray, future: np.ndarray, valid: np.ndarray) -> dict:
    """One window's choice as a dict (module docstring).

    Args:
        result: the window's :class:`~renderworld.planning.checked.CheckedPlan`.
        raw: [S, 2] the learned plan, metres, current ego frame.
        future: [S, 2] the ground-truth future positions.
        valid: [S] bool, steps inside the scene.
    """
    c = result.candidates
    last = int(np.flatnonzero(valid)[-1]) if valid.any() else -1

    def l2(xy):
        return float(np.hypot(*(xy[last] - future[last]))) if last >= 0 else float("nan")

    b = c.best
    held = not np.allclose(c.waypoints[0, 1:], raw[1:], atol=1e-3)  # the first: its start moved
    return {
        "kind": c.kind[b], "offset": float(c.offset_m[b]), "horizon_step": last,
        "l2_raw": l2(raw), "l2_checked": l2(result.trajectory), "l2_plan_cand": l2(c.waypoints[0]),
        "plan_held": bool(held),
        "plan": {k: float(getattr(c, k)[0]) for k in SUBSCORES},
        "plan_choice": float(c.choice[0]),
        "best": {k: float(getattr(c, k)[b]) for k in SUBSCORES},
        "best_choice": float(c.choice[b]),
    }  # fmt: skip


def _fails(p: dict) -> list:
    return [k for k in ("NC", "DAC", "TTC", "C") if p[k] < 1] + (["EP"] if p["EP"] < 0.8 else [])


def _by_group(full: list[dict], top: int = 5) -> list[str]:
    """Markdown rows per behaviour and for the ``top`` scenes adding the most L2 (module
    docstring); none where the records carry no scene."""
    if not full or "scene" not in full[0]:
        return []
    out = []
    for title, key in (("behaviour", "behaviour"), ("scene", "scene")):
        groups = defaultdict(list)
        for r in full:
            groups[r[key] or "(none)"].append(r)
        added = {k: sum(r["l2_checked"] - r["l2_raw"] for r in rs) for k, rs in groups.items()}
        order = sorted(groups, key=lambda k: -added[k])[: None if key == "behaviour" else top]
        out += ["", f"| {title} | windows | L2 at 3 s raw (m) | checked (m) | L2 added (m, sum) "
                "| GT-box contacts at 3 s raw / checked |",
                "|---|---|---|---|---|---|"]  # fmt: skip
        for k in order:
            rs = groups[k]
            hits = (f"{sum(bool(r.get('hit_raw')) for r in rs)} / "
                    f"{sum(bool(r.get('hit_checked')) for r in rs)}")  # fmt: skip
            out.append(f"| {k} | {len(rs)} | {np.mean([r['l2_raw'] for r in rs]):.2f} "
                       f"| {np.mean([r['l2_checked'] for r in rs]):.2f} | {added[k]:.1f} "
                       f"| {hits} |")  # fmt: skip
    return out


def summary(records: list[dict]) -> str:
    """Markdown tables of one command's records (module docstring)."""
    full = [r for r in records if r["horizon_step"] == 5]
    lines = [f"{len(records)} windows, {len(full)} with the full 3 s horizon (tables: those)", ""]
    lines += ["| chosen | windows | L2 at 3 s raw (m) | checked (m) | plan's candidate (m) |",
              "|---|---|---|---|---|"]  # fmt: skip
    groups = defaultdict(list)
    for r in full:
        groups[r["kind"] if r["kind"] != "plan" or r["offset"] else "plan, no offset"].append(r)
    groups["all"] = full
    for kind, rs in sorted(groups.items(), key=lambda kv: (kv[0] == "all", -len(kv[1]))):
        m = {k: np.mean([r[k] for r in rs]) for k in ("l2_raw", "l2_checked", "l2_plan_cand")}
        lines.append(f"| {kind} | {len(rs)} | {m['l2_raw']:.2f} | {m['l2_checked']:.2f} "
                     f"| {m['l2_plan_cand']:.2f} |")  # fmt: skip
    lost = [r for r in full if r["kind"] != "plan" or r["offset"]]
    fails = defaultdict(int)
    for r in lost:
        fails[", ".join(_fails(r["plan"])) or "none (a margin)"] += 1
    lines += ["", f"The learned plan lost in {len(lost)} windows; its failed sub-scores:", "",
              "| failed | windows |", "|---|---|"]  # fmt: skip
    lines += [f"| {k} | {v} |" for k, v in sorted(fails.items(), key=lambda kv: -kv[1])]
    held = [r for r in full if r["kind"] == "plan" and not r["offset"] and r["plan_held"]]
    if held:
        lines += ["", f"The plan won but was held back by IDM in {len(held)} windows: L2 at 3 s "
                  f"raw {np.mean([r['l2_raw'] for r in held]):.2f} m, held "
                  f"{np.mean([r['l2_checked'] for r in held]):.2f} m"]  # fmt: skip
    hit = [r for r in full if r.get("hit_checked")]
    if "hit_checked" in (full[0] if full else {}):
        kinds = defaultdict(int)
        for r in hit:
            kinds[(r["kind"] if r["kind"] != "plan" or r["offset"] else "plan, no offset")
                  + (", the raw plan too" if r["hit_raw"] else "")] += 1  # fmt: skip
        lines += ["", f"The checked plan meets a ground-truth box at 3 s in {len(hit)} windows "
                  f"(the raw plan in {sum(r['hit_raw'] for r in full)}):", "",
                  "| driven | windows |", "|---|---|"]  # fmt: skip
        lines += [f"| {k} | {v} |" for k, v in sorted(kinds.items(), key=lambda kv: -kv[1])]
    lines += _by_group(full)
    gt = [r for r in full if "gt" in r]
    if gt:
        refused = defaultdict(int)
        for r in gt:
            why = _fails(r["gt"])
            if "C" in why:
                why[why.index("C")] = f"C ({r['gt_comfort_worst']})"
            refused[", ".join(why)] += 1
        n_bad = len(gt) - refused.pop("", 0)
        lines += ["", f"The ground-truth future, scored by the same check: refused in {n_bad} of "
                  f"{len(gt)} windows", "", "| failed | windows |", "|---|---|"]  # fmt: skip
        lines += [f"| {k} | {v} |" for k, v in sorted(refused.items(), key=lambda kv: -kv[1])]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_eval_args(ap, "outputs/checked_choice")
    ap.add_argument("--check", nargs="*", default=[], help="CheckConfig knobs, KNOB=VALUE")
    args = ap.parse_args()
    check_files(args)

    records: list[dict] = []
    pending: list = []
    original_check, original_checked = checked_mod.check_plan, wmp.checked_plans

    def check_plan(*a, **k):
        result = original_check(*a, **k)
        pending.append(result)
        return result

    calls, seen = [0], set()
    truth: list = []  # [(future [S, 2], valid [S])] of the batch's windows, in planning order
    gt_scores: list = []
    original_score = checked_mod.score_candidates

    def score_candidates(cands, scene, past, cfg, limits=None, dt=KEYFRAME_DT, previous=None):
        out = original_score(cands, scene, past, cfg, limits, dt, previous)
        fut, valid = truth.pop(0) if truth else (None, None)
        if fut is not None and valid.all():  # the logged future, beside, not chosen from
            one = Candidates(fut[None], ["gt"], np.zeros(1), np.zeros(1), cands.reference_m,
                             cands.path)  # fmt: skip
            g = original_score(one, scene, past, cfg, limits, dt, previous)
            gt_scores.append({"gt": {k: float(getattr(g, k)[0]) for k in SUBSCORES},
                              "gt_comfort_worst": g.comfort_worst[0]})  # fmt: skip
        else:
            gt_scores.append({})
        return out

    def checked_plans(stage, model, batch, setting, poses):
        # Called twice per batch: the GT command's plans first, then the history command's;
        # the evaluation's pictures plan some windows again (kept once, by sample token).
        pending.clear()
        gt_scores.clear()
        fut = batch["future_poses"][..., :2].double().cpu().numpy()
        valid = batch["future_mask"].bool().cpu().numpy()[:, : fut.shape[1]]
        truth[:] = list(zip(fut, valid))
        out = original_checked(stage, model, batch, setting, poses)
        command = ("gt", "history")[calls[0] % 2]
        calls[0] += 1
        raw = poses[..., :2].double().cpu().numpy()
        boxes = batch["future_boxes"][..., :5].cpu().numpy()
        boxes_ok = batch["future_boxes_mask"].cpu().numpy().astype(bool)
        tokens = batch["meta"]["sample_tokens"][stage.settings.history - 1]
        scenes = batch["meta"].get("scene", [""] * len(tokens))
        about = batch["meta"].get("scene_description", [""] * len(tokens))
        for i, res in enumerate(pending):
            if (command, tokens[i]) not in seen:
                seen.add((command, tokens[i]))
                rec = window_record(res, raw[i], fut[i], valid[i])
                extra = gt_scores[i] if i < len(gt_scores) else {}
                if valid[i].all():  # at 3 s, as the evaluation's collision count
                    trajs = np.stack([res.trajectory, raw[i]]).astype(np.float64)
                    hits, _ = collisions_with_boxes(trajs, boxes[i], boxes_ok[i])
                    extra = {**extra, "hit_checked": bool(hits[0, -1]),
                             "hit_raw": bool(hits[1, -1])}  # fmt: skip
                where = {"scene": scenes[i], "behaviour": behaviour_of(about[i]) or ""}
                records.append({"command": command, "token": tokens[i], **where, **rec, **extra})
        return out

    checked_mod.check_plan, wmp.checked_plans = check_plan, checked_plans
    checked_mod.score_candidates = score_candidates
    run_dir = Path(args.out).resolve()
    knobs = ", ".join(kv.replace("=", ": ", 1) for kv in args.check)
    try:
        evaluate_world_model(args, run_dir, *([f"check={{{knobs}}}"] if args.check else []))
    finally:
        checked_mod.check_plan, wmp.checked_plans = original_check, original_checked
        checked_mod.score_candidates = original_score
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "checked_choice.json").write_text(json.dumps(records, indent=1))
    print(summary([r for r in records if r["command"] == "gt"]))


if __name__ == "__main__":
    main()
