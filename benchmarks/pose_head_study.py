"""The pose head alone: what its inputs and training buy in heading error, L2 and collisions.

Trains only the :class:`~renderworld.world.pose.PoseHead` of ``experiment=world_model_mini``
(pose loss with the experiment's yaw weight and mirroring, AdamW, linear warm-up then cosine, batch
4) on the main job's training windows (the mini fixture's train split + the scenario library), then
scores it on val splits: heading error (degrees, median / mean over windows) and L2 (m) at 1 / 2 /
3 s, and collisions with GT boxes at 3 s. A few hundred steps take ~20 s on a 2-core CPU, so input
and training variants can be compared over seeds before a full world-model training.

Variants (``--variant``, comma-separated): ``pool8`` (8 x 8 BEV pooling), ``wide`` (a wider BEV
CNN), ``nobev`` (no bird's-eye view), ``drop`` (dropout 0.2 in the MLP), ``motion`` (three more BEV
channels: where the object-CV movers will be at +1 / +2 / +3 s), ``kin`` / ``nokin`` (the head
reads :func:`~renderworld.world.pose.kinematic_features` or not, whatever the experiment's
``stage.pose_kinematics``). ``--tta`` averages each prediction with its mirrored scene's;
``--brake`` stops the plan ``--gap`` m short of the first step where the ego box (inflated by
``--margin`` m) meets a mover moved at its history velocity.

Usage::

    python benchmarks/pose_head_study.py --data-root data/sim_mini \\
        --tokenizer outputs/demo/tokenizer/checkpoints/last.pt --library data/sim_scenarios \\
        --val data/sim_mini data/sim_mini_s77 data/sim_interactions@v1.0-interactions \\
        [--steps 800] [--warmup-steps 0] [--clip 1] [--seed 0] [--lr 1e-3]
        [--variant kin,motion] [--tta] [--brake --margin 0.5 --gap 3]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hydra import compose, initialize_config_dir  # noqa: E402

from renderworld.constants import EGO_LENGTH, EGO_WIDTH  # noqa: E402
from renderworld.metrics import PlanningMetric  # noqa: E402
from renderworld.training.registry import get_stage  # noqa: E402
from renderworld.training.stages.world_model.pose_warp import (  # noqa: E402
    mirror_command,
    mirror_poses,
)
from renderworld.world.baselines import constant_turn_rate_poses  # noqa: E402
from renderworld.world.movers import movable_mask, object_cv_frames  # noqa: E402
from renderworld.world.pose import BEV_GROUPS, PoseHead, bev_channels, pose_loss  # noqa: E402


def run_config(data_root: str, tokenizer: str, library: str | None):
    """The experiment's config on ``data_root`` (``path@version`` picks a dataset version)."""
    root, _, version = data_root.partition("@")
    ov = ["experiment=world_model_mini", f"dataset.data_root={root}",
          f"stage.tokenizer_ckpt={tokenizer}"]  # fmt: skip
    ov += [f"dataset.version={version}"] if version else []
    ov += [f"stage.extra_train_roots=[{library}]"] if library else []
    with initialize_config_dir(str(ROOT / "configs"), version_base="1.3"):
        return compose("train", overrides=ov)


def apply_variants(head: nn.Module, variants: set[str]) -> None:
    """Swap parts of a fresh pose head for the named variants (see the module doc)."""
    hid = head.bev[8].out_features
    if "pool8" in variants:
        head.bev[6], head.bev[8] = nn.AdaptiveAvgPool2d(8), nn.Linear(32 * 64, hid)
    if "wide" in variants:
        head.bev = nn.Sequential(
            nn.Conv2d(len(BEV_GROUPS), 32, 3, padding=1), nn.GELU(),
            nn.Conv2d(32, 32, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(64, 64, 3, stride=2, padding=1), nn.GELU(),
            nn.AdaptiveAvgPool2d(4), nn.Flatten(), nn.Linear(64 * 16, hid), nn.GELU(),
        )  # fmt: skip
    if "motion" in variants:
        first = head.bev[0]
        head.bev[0] = nn.Conv2d(first.in_channels + 3, first.out_channels, 3, 2, 1)
    if "drop" in variants:
        head.mlp.insert(2, nn.Dropout(0.2))


class _NoBev(nn.Module):
    def __init__(self, n: int):
        super().__init__()
        self.n = n

    def forward(self, x):
        return x.new_zeros(x.shape[0], self.n)


def predict(head, grid, variants, hist, cmd, occ_hist, flip=False):
    """Poses [B, S, 3] of the head from history poses, command and history occupancy."""
    cur = occ_hist[:, -1]
    bev = bev_channels(cur)
    if "motion" in variants:
        moved = movable_mask(object_cv_frames(occ_hist, hist.double(), 6, grid)[:, [1, 3, 5]])
        now = movable_mask(cur).any(-1).float()[:, None]
        bev = torch.cat([bev, moved.any(-1).float() * (1 - now)], 1)
    if flip:
        return head(mirror_poses(hist), mirror_command(cmd), bev.flip(3))[0]
    return head(hist, cmd, bev)[0]


def brake(pred, hist, occ_hist, grid, margin: float, gap: float):
    """The plan stopped ``gap`` m short of its first step that meets a moved mover."""
    movers = movable_mask(object_cv_frames(occ_hist, hist.double(), pred.shape[1], grid)).any(-1)
    xs = grid.range_min[0] + (torch.arange(grid.shape[0]) + 0.5) * grid.voxel_size[0]
    ys = grid.range_min[1] + (torch.arange(grid.shape[1]) + 0.5) * grid.voxel_size[1]
    slack = grid.voxel_size[0] / 2
    out = pred.clone()
    for b in range(pred.shape[0]):
        path = torch.cat([pred.new_zeros(1, 3), pred[b]], 0)
        arc = torch.cat([pred.new_zeros(1), (path[1:, :2] - path[:-1, :2]).norm(dim=-1).cumsum(0)])
        hit = None
        for k in range(pred.shape[1]):
            cells = movers[b, k].nonzero()
            x, y, yaw = pred[b, k]
            dx, dy = xs[cells[:, 0]] - x, ys[cells[:, 1]] - y
            lon = torch.cos(yaw) * dx + torch.sin(yaw) * dy
            lat = -torch.sin(yaw) * dx + torch.cos(yaw) * dy
            near = (lon.abs() <= EGO_LENGTH / 2 + margin + slack) & (
                lat.abs() <= EGO_WIDTH / 2 + margin + slack
            )
            if near.any():
                hit = k
                break
        if hit is None:
            continue
        stop = max(0.0, float(arc[hit + 1]) - gap)
        for j in range(pred.shape[1]):
            a = min(float(arc[j + 1]), stop)
            i = int(torch.searchsorted(arc, torch.tensor(a), right=True).clamp(1, len(arc) - 1))
            t = (a - float(arc[i - 1])) / max(float(arc[i] - arc[i - 1]), 1e-6)
            out[b, j] = path[i - 1] + t * (path[i] - path[i - 1])
    return out


def heading_deg(a, b):
    d = a - b
    return torch.rad2deg(torch.atan2(torch.sin(d), torch.cos(d)).abs())


@torch.no_grad()
def score(head, args, variants, data_root: str) -> str:
    cfg = run_config(data_root, args.tokenizer, None)
    stage = get_stage(cfg.stage.name, cfg.stage._target_module_)(cfg)
    h = stage.settings.history
    errs, l2s, ctr = [], [], []
    plan = PlanningMetric(stage.settings.future)
    head.eval()
    for batch in DataLoader(stage.build_val_dataset(cfg), batch_size=8):
        hist, fut, cmd = batch["history_poses"].float(), batch["future_poses"].float(), batch[
            "command"
        ].long()  # fmt: skip
        occ = batch["occ"][:, :h]
        pred = predict(head, stage.grid, variants, hist, cmd, occ)
        if args.tta:
            pred = 0.5 * (pred + mirror_poses(predict(head, stage.grid, variants, hist, cmd, occ,
                                                      flip=True)))  # fmt: skip
        if args.brake:
            pred = brake(pred, hist, occ, stage.grid, args.margin, args.gap)
        plan.update(pred[..., :2], batch["future_traj"].float(), valid=batch["future_mask"].bool(),
                    agent_boxes=list(batch["future_boxes"][..., :5].numpy()),
                    agent_valid=list(batch["future_boxes_mask"].numpy()))  # fmt: skip
        errs.append(heading_deg(pred[..., 2], fut[..., 2]))
        l2s.append((pred[..., :2] - fut[..., :2]).norm(dim=-1))
        ctr_poses = constant_turn_rate_poses(hist.double(), fut.shape[1]).float()
        ctr.append(heading_deg(ctr_poses[..., 2], fut[..., 2]))
    head.train()
    err, l2, ctr = torch.cat(errs).numpy(), torch.cat(l2s).numpy(), torch.cat(ctr).numpy()
    res = plan.compute()
    parts = []
    for sec, k in ((1, 1), (2, 3), (3, 5)):
        parts.append(f"{sec} s: heading {np.median(err[:, k]):.2f} / {err[:, k].mean():.2f} deg, "
                     f"L2 {l2[:, k].mean():.2f} m")  # fmt: skip
    coll = (f"{res['collision_boxes_hits_at_horizon@3s']} / "
            f"{res['collision_boxes_evaluated_at_horizon@3s']}")  # fmt: skip
    return (f"{Path(data_root.partition('@')[0]).name}: " + "; ".join(parts)
            + f"; collisions at 3 s {coll} (CTR heading at 1 s "
            f"{np.median(ctr[:, 1]):.2f} / {ctr[:, 1].mean():.2f} deg)")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data-root", required=True)
    ap.add_argument("--tokenizer", required=True, help="the world model's tokenizer checkpoint")
    ap.add_argument("--library", default=None, help="scenario library data root (training)")
    ap.add_argument("--val", nargs="+", required=True, help="data roots (path[@version]) to score")
    ap.add_argument("--steps", type=int, default=800)
    ap.add_argument("--warmup-steps", type=int, default=0, help="steps of a first schedule")
    ap.add_argument("--clip", type=float, default=1.0, help="gradient-norm clip of the head")
    ap.add_argument("--seed", type=int, default=0)
    lr_help = "default: the experiment's optimizer.lr x stage.pose_lr_scale"
    ap.add_argument("--lr", type=float, default=None, help=lr_help)
    ap.add_argument("--weight-decay", type=float, default=0.01)
    ap.add_argument("--yaw-weight", type=float, default=None, help="default: the experiment's")
    ap.add_argument("--variant", default="")
    ap.add_argument("--tta", action="store_true")
    ap.add_argument("--brake", action="store_true")
    ap.add_argument("--margin", type=float, default=0.5)
    ap.add_argument("--gap", type=float, default=3.0)
    args = ap.parse_args()
    variants = {v for v in args.variant.split(",") if v}
    torch.manual_seed(args.seed)
    cfg = run_config(args.data_root, args.tokenizer, args.library)
    stage = get_stage(cfg.stage.name, cfg.stage._target_module_)(cfg)
    train_set, _ = stage.build_datasets(cfg)
    head = stage.build_model(cfg).pose
    if variants & {"kin", "nokin"}:
        head = PoseHead(head.history, head.steps, anchors=head.anchors,
                        kinematics="kin" in variants)  # fmt: skip
    if args.lr is None:
        args.lr = float(cfg.optimizer.lr) * stage.settings.pose_lr_scale
    apply_variants(head, variants)
    if "nobev" in variants:
        head.bev = _NoBev(head.bev[8].out_features)
    st, h = stage.settings, stage.settings.history
    yaw_w = st.pose_yaw_weight if args.yaw_weight is None else args.yaw_weight
    opt = torch.optim.AdamW(head.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    loader = DataLoader(train_set, batch_size=4, shuffle=True, drop_last=True,
                        generator=torch.Generator().manual_seed(args.seed))  # fmt: skip
    it, t0 = iter(loader), time.time()
    # --warmup-steps: a first schedule of its own (the stage's pose_warmup_steps), then --steps.
    schedule = [(i, args.warmup_steps) for i in range(args.warmup_steps)]
    schedule += [(i, args.steps) for i in range(args.steps)]
    for i, n in schedule:
        try:
            batch = next(it)
        except StopIteration:
            it = iter(loader)
            batch = next(it)
        scale = min(1.0, (i + 1) / 20) * 0.5 * (1 + math.cos(math.pi * i / n))
        for g in opt.param_groups:
            g["lr"] = args.lr * scale
        hist, fut = batch["history_poses"].float(), batch["future_poses"].float()
        cmd, valid, occ = batch["command"].long(), batch["future_mask"].bool(), batch["occ"][:, :h]
        loss = 0.0
        for flip in (False, True):  # the scene and its mirror, as the stage trains
            pred = predict(head, stage.grid, variants, hist, cmd, occ, flip=flip)
            gt = mirror_poses(fut) if flip else fut
            loss = loss + 0.5 * pose_loss(pred, gt, valid, yaw_weight=yaw_w)["pose"]
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(head.parameters(), args.clip)
        opt.step()
    print(f"pose head, {args.warmup_steps} + {args.steps} steps, lr {args.lr:g}, "
          f"clip {args.clip:g}, seed {args.seed}, variants {sorted(variants) or '-'}"
          f"{', tta' if args.tta else ''}"
          f"{f', brake (margin {args.margin} m, gap {args.gap} m)' if args.brake else ''}: "
          f"trained in {time.time() - t0:.0f} s")  # fmt: skip
    for root in args.val:
        print("  " + score(head, args, variants, root))


if __name__ == "__main__":
    main()
