"""Which part of a trained pose-warp world model's ego pose costs its forecast: heading or position.

Evaluates a world-model checkpoint with ``tools/eval.py``'s code, once per mode, with the
predicted future poses [B, S, 3] (x, y, yaw; current ego frame) changed before the forecast:

* ``model``: as predicted (the stage's own row);
* ``gt_yaw``: the predicted positions, the ground-truth headings (a reference: reads the future);
* ``gt_xy``: the ground-truth positions, the predicted headings (a reference);
* ``ctr_yaw``: the predicted positions, headings at the last history step's turn rate
  (future-free);
* ``path_yaw``: the predicted positions, headings along the predicted path (at each point the
  mean direction of the chords before and after it; future-free).

Everything else (movers, token network, metrics) is the stage's. Prints the 3D-Occ model row of
each mode: mIoU, movers' mIoU, L2 and mean heading error at 1 / 2 / 3 s; each mode's full
evaluation lands in ``<out>/<mode>/``. Score development splits with it, not test splits.

Usage::

    python benchmarks/pose_error_split.py --data-root data/sim_dev --split all \\
        --tokenizer outputs/demo/tokenizer/checkpoints/last.pt \\
        --world-model outputs/demo/world_model/checkpoints/last.pt --out outputs/pose_error_split
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import renderworld.training.stages.world_model.pose_warp as wmp  # noqa: E402
from benchmarks.dev_eval import add_eval_args, check_files, evaluate_world_model  # noqa: E402
from renderworld.world import constant_turn_rate_poses  # noqa: E402

MODES = ("model", "gt_yaw", "gt_xy", "ctr_yaw", "path_yaw")


def changed_poses(mode: str, poses, hist, future):
    """[B, S, 3] ``poses`` with the part ``mode`` names replaced (module docstring).

    Args:
        mode: one of :data:`MODES`.
        poses: [B, S, 3] predicted (x, y, yaw), metres and radians, current ego frame.
        hist: [B, H, 3] history poses, the last one the current frame (zeros).
        future: [B, S, 3] ground-truth future poses.
    """
    out = poses.clone()
    if mode == "gt_yaw":
        out[..., 2] = future[..., 2].to(out)
    elif mode == "gt_xy":
        out[..., :2] = future[..., :2].to(out)
    elif mode == "ctr_yaw":
        out[..., 2] = constant_turn_rate_poses(hist, out.shape[1])[..., 2].to(out)
    elif mode == "path_yaw":
        out[..., 2] = path_headings(hist, out)
    elif mode != "model":
        raise ValueError(f"--modes: unknown mode {mode!r}, expected one of {MODES}")
    return out


def path_headings(hist, poses, min_step: float = 0.2):
    """[B, S] headings along the path of ``poses``' positions (radians, current ego frame).

    At each point the direction of the sum of the unit chords before and after it (the last
    point: its chord before); the chord before the first point starts at the current pose, the
    one before that at the last history pose. A chord shorter than ``min_step`` metres has no
    direction: the predicted heading stays where every chord at a point is that short.
    """
    xy = torch.cat([hist[:, -2:, :2].to(poses), poses[..., :2]], dim=1)  # [B, S + 2, 2]
    chord = xy[:, 1:] - xy[:, :-1]  # [B, S + 1, 2]: chord k ends at point k (0 = now)
    n = chord.norm(dim=-1, keepdim=True)
    unit = torch.where(n > min_step, chord / n.clamp_min(1e-9), torch.zeros_like(chord))
    before, after = unit[:, 1:], torch.cat([unit[:, 2:], torch.zeros_like(unit[:, :1])], dim=1)
    d = before + after  # [B, S, 2]
    ok = d.norm(dim=-1) > 1e-6
    return torch.where(ok, torch.atan2(d[..., 1], d[..., 0]), poses[..., 2])


def _patch(mode: str):
    """Wrap ``pose_forecast`` so that the model's predicted poses are changed per ``mode``."""
    original = wmp.pose_forecast

    def pose_forecast(stage, model, batch, setting):
        predict = model.predict_poses

        def changed(hist, *args, **kwargs):
            poses, extra = predict(hist, *args, **kwargs)
            return changed_poses(mode, poses, hist, batch["future_poses"]), extra

        model.predict_poses = changed
        try:
            return original(stage, model, batch, setting)
        finally:
            del model.predict_poses

    wmp.pose_forecast = pose_forecast
    return original


def _model_row(csv_path: Path) -> dict:
    with open(csv_path, newline="") as f:
        for row in csv.DictReader(f):
            if row.get("setting") == "3D-Occ" and row.get("method") == "model":
                return row
    raise ValueError(f"{csv_path}: no 3D-Occ 'model' row")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_eval_args(ap, "outputs/pose_error_split")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    args = ap.parse_args()
    check_files(args)

    rows = {}
    for mode in args.modes:
        original = _patch(mode)
        run_dir = Path(args.out).resolve() / mode
        try:
            evaluate_world_model(args, run_dir)
        finally:
            wmp.pose_forecast = original
        rows[mode] = _model_row(run_dir / "world_model_eval.csv")
    print("| poses | mIoU 1 / 2 / 3 s | movers' mIoU 1 / 2 / 3 s | L2 1 / 2 / 3 s (m) "
          "| heading error, mean, 1 / 2 / 3 s (deg) |")  # fmt: skip
    print("|---|---|---|---|---|")
    for mode, r in rows.items():
        cols = [" / ".join(f"{float(r[q.format(h)]):.2f}" for h in (1, 2, 3))
                for q in ("miou_{}s_pct", "movers_miou_{}s_pct", "l2_at_horizon_{}s_m",
                          "heading_mean_{}s_deg")]  # fmt: skip
        print(f"| {mode} | " + " | ".join(cols) + " |")


if __name__ == "__main__":
    main()
