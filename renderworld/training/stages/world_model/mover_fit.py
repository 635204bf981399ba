"""Fitting the mover head (``stage.movers: learned``) on the training windows' road users.

Before the joint training (after the pose head's warm-up) every training window is read once:
its current frame's movers are tracked through its history
(:func:`renderworld.world.tracks.track_movers`) and each is matched to its annotated box (the
nearest box of its class within :data:`MATCH_M` of its centroid); that road user's boxes in the
future frames, found by its instance index, give the target: its displacement at each future
step (steps where it is not annotated are masked). The head is then fitted alone for
``stage.mover_fit_steps`` steps on random batches of movers (each scene also mirrored about the
ego's x axis), Huber loss on the displacements. Only annotations of the **training** windows
are read; at test time the head reads occupancy alone.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader

from renderworld.constants import GridSpec
from renderworld.world.mover_head import MoverHead, MoverInputs, mirror_inputs, mover_inputs
from renderworld.world.tracks import MoverTrack, track_movers

__all__ = ["MATCH_M", "MoverSamples", "fit_mover_head", "mover_samples", "mover_targets"]

log = logging.getLogger("renderworld.training")

#: A mover's centroid and its box centre lie at most this far apart, metres.
MATCH_M = 3.0


def mover_targets(
    tracks: list[MoverTrack],
    current_boxes: np.ndarray,
    current_mask: np.ndarray,
    future_boxes: np.ndarray,
    future_mask: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each mover's true displacements, by the identity of its annotated box.

    Args:
        tracks: the current frame's movers.
        current_boxes: [M, 7] boxes of the current frame (x, y, length, width, yaw, class,
            instance), current ego frame; current_mask: [M] bool.
        future_boxes: [S, M, 7] boxes of the future frames, same frame; future_mask: [S, M].

    Returns:
        (displacements [N, S, 2] float32 metres, valid [N, S] bool, instance [N] int: -1 when
        no box matched).
    """
    n, s = len(tracks), future_boxes.shape[0]
    disp = np.zeros((n, s, 2), dtype=np.float32)
    valid = np.zeros((n, s), dtype=bool)
    inst = np.full(n, -1, dtype=np.int64)
    cur = np.asarray(current_boxes)[np.asarray(current_mask, dtype=bool)]
    for i, tr in enumerate(tracks):
        d = np.where(cur[:, 5] == tr.cls, np.hypot(*(cur[:, :2] - tr.centroid).T), np.inf)
        if not len(d) or d.min() > MATCH_M:
            continue
        box = cur[int(np.argmin(d))]
        inst[i] = int(box[6])
        for k in range(s):
            fut = future_boxes[k][np.asarray(future_mask[k], dtype=bool)]
            same = fut[:, 6] == box[6]
            if same.any():
                disp[i, k] = fut[same][0, :2] - box[:2]
                valid[i, k] = True
    return disp, valid, inst


class MoverSamples:
    """Movers of many windows: inputs, target displacements and their validity, concatenated."""

    def __init__(self, inputs: list[MoverInputs], targets: list[np.ndarray], valid: list):
        self.inputs = MoverInputs(*(np.concatenate([getattr(x, k) for x in inputs])
                                    for k in ("feats", "patches", "base")))  # fmt: skip
        self.targets = np.concatenate(targets)
        self.valid = np.concatenate(valid)

    def __len__(self) -> int:
        return len(self.inputs)


def mover_samples(batch: dict, history: int, future: int, grid: GridSpec) -> MoverSamples:
    """The movers of a collated batch of world-model windows, with their targets."""
    occ = batch["occ"][:, :history].cpu().numpy()
    poses = batch["history_poses"].double().cpu().numpy()
    names = ("current_boxes", "current_boxes_mask", "future_boxes", "future_boxes_mask")
    boxes = [batch[k].cpu().numpy() for k in names]
    inputs, targets, valid = [], [], []
    for i in range(occ.shape[0]):
        tracks = track_movers(occ[i], poses[i], grid)
        inputs.append(mover_inputs(occ[i, -1], poses[i], tracks, grid, future))
        t, v, _ = mover_targets(tracks, *(b[i] for b in boxes))
        targets.append(t)
        valid.append(v)
    return MoverSamples(inputs, targets, valid)


def _loss(head: MoverHead, inp: MoverInputs, target: np.ndarray, valid: np.ndarray) -> torch.Tensor:
    dev = next(head.parameters()).device

    def put(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(dev)

    pred = head(put(inp.feats), put(inp.patches), put(inp.base))
    err = torch.nn.functional.smooth_l1_loss(pred, put(target), reduction="none")
    m = put(valid).float()
    return (err.sum(-1) * m).sum() / m.sum().clamp_min(1.0)


def fit_mover_head(
    head: MoverHead,
    dataset: Any,
    history: int,
    future: int,
    grid: GridSpec,
    steps: int,
    lr: float,
    batch_size: int = 256,
    seed: int = 0,
    weight_decay: float = 1e-4,
    progress: bool = False,
) -> dict[str, float]:
    """Fit ``head`` alone on the movers of ``dataset``'s windows (module docstring).

    Args:
        head: the mover head (trained in place, on its own device).
        dataset: world-model training windows (items with ``occ``, ``history_poses`` and boxes).
        history, future: H and S of the windows; grid: the occupancy grid.
        steps: optimiser steps; lr: peak learning rate (5 % linear warm-up, then cosine).
        batch_size: movers per step; seed: sampling seed; weight_decay: AdamW's.
        progress: a tqdm bar while reading the windows.

    Returns:
        ``{"mover_fit/movers", "mover_fit/first_loss", "mover_fit/last_loss", "mover_fit/read_s",
        "mover_fit/fit_s"}``.

    Raises:
        ValueError: naming ``stage.mover_fit_steps`` when the windows hold no annotated mover.
    """
    t0 = time.perf_counter()
    loader = DataLoader(dataset, batch_size=16, shuffle=False, num_workers=0)
    if progress:
        from tqdm import tqdm

        loader = tqdm(loader, desc="mover head: reading windows", unit="batch")
    parts = [mover_samples(b, history, future, grid) for b in loader]
    data = MoverSamples(
        [p.inputs for p in parts], [p.targets for p in parts], [p.valid for p in parts]
    )
    keep = np.flatnonzero(data.valid.any(1))
    if not len(keep):
        raise ValueError(
            f"stage.mover_fit_steps={steps}: the training windows hold no mover matched to an "
            "annotated box (boxes need instance indices: re-run tools/create_data.py)"
        )
    t1 = time.perf_counter()
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    head.train()
    opt = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=weight_decay)
    warm = max(1, round(0.05 * steps))  # linear warm-up, then a cosine to zero

    def rate(i: int) -> float:
        if i < warm:
            return (i + 1) / warm
        return 0.5 * (1.0 + np.cos(np.pi * (i - warm) / max(1, steps - warm)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, rate)
    losses = []
    inp = data.inputs
    for it in range(steps):
        idx = keep[rng.integers(0, len(keep), batch_size)]
        sel = MoverInputs(inp.feats[idx], inp.patches[idx], inp.base[idx])
        target = data.targets[idx]
        if it % 2:  # the mirrored scene
            sel = mirror_inputs(sel, history)
            target = target * np.array([1.0, -1.0], dtype=np.float32)
        loss = _loss(head, sel, target, data.valid[idx])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    head.eval()
    return {
        "mover_fit/movers": float(len(keep)),
        "mover_fit/first_loss": float(np.mean(losses[:20])) if losses else float("nan"),
        "mover_fit/last_loss": float(np.mean(losses[-20:])) if losses else float("nan"),
        "mover_fit/read_s": t1 - t0,
        "mover_fit/fit_s": time.perf_counter() - t1,
    }
