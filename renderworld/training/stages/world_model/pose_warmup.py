"""Fit the pose head alone before the joint training (``stage.pose_warmup_steps``).

In the joint training the pose head gets as many updates as the token network (800 on the mini
job) and ends under-trained: trained alone for longer on the same windows, its heading error and
L2 keep falling (docs/world_model.md). A pose-only step costs a few per cent of a joint step (no
tokenizer, no token network), so the head is fitted first on its own, then trained on jointly.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch.utils.data import DataLoader, Dataset
from tqdm.auto import tqdm

from renderworld.training.stages.world_model.pose_warp import pose_terms

__all__ = ["WARMUP_CLIP", "WARMUP_WARMUP_STEPS", "warm_up_pose_head"]

#: Gradient-norm clip of the pose head's own steps (the joint training clips the whole model at
#: ``trainer.grad_clip``; alone, 1 gave the lower heading error: docs/world_model.md).
WARMUP_CLIP = 1.0
#: Linear learning-rate warm-up of those steps, then cosine to zero.
WARMUP_WARMUP_STEPS = 20


def warm_up_pose_head(
    stage: Any,
    model: Any,
    dataset: Dataset,
    steps: int,
    *,
    lr: float,
    weight_decay: float,
    batch_size: int,
    seed: int,
    progress: bool = True,
) -> dict[str, float]:
    """Train ``model.pose`` alone for ``steps`` AdamW steps on the stage's pose loss.

    Only the pose head's parameters change (the token network and the copy bonus are left as
    they are); the batches are drawn from ``dataset`` in an order set by ``seed`` alone.

    Args:
        stage: the ``WorldModelStage`` (its settings give the pose loss; ``transfer_batch``).
        model: a ``PoseWarpWorldModel`` in training mode.
        dataset: the training windows.
        steps: optimizer steps (> 0).
        lr: peak learning rate (reached after :data:`WARMUP_WARMUP_STEPS`, then cosine to 0).
        weight_decay: AdamW weight decay.
        batch_size: windows per step.
        seed: seed of the batch order.
        progress: show a progress bar.

    Returns:
        ``pose_warmup/first_loss`` and ``pose_warmup/last_loss``: the mean pose loss (metres +
        yaw weight x radians) over the first and the last 20 steps.

    Raises:
        ValueError: ``steps`` < 1, or a dataset smaller than one batch.
    """
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if len(dataset) < batch_size:
        raise ValueError(f"dataset: {len(dataset)} windows, fewer than one batch of {batch_size}")
    head = model.pose
    device = next(head.parameters()).device
    opt = torch.optim.AdamW(head.parameters(), lr=lr, weight_decay=weight_decay)
    gen = torch.Generator().manual_seed(int(seed) * 1_000_003 + 17)
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=True, drop_last=True,
                        generator=gen, collate_fn=stage.collate_fn())  # fmt: skip
    losses: list[float] = []
    batches = iter(loader)
    for i in tqdm(range(steps), desc="pose warm-up", disable=not progress, dynamic_ncols=True):
        try:
            batch = next(batches)
        except StopIteration:
            batches = iter(loader)
            batch = next(batches)
        ramp = min(1.0, (i + 1) / WARMUP_WARMUP_STEPS)
        for g in opt.param_groups:
            g["lr"] = lr * ramp * 0.5 * (1.0 + math.cos(math.pi * i / steps))
        batch = stage.transfer_batch(batch, device)
        loss = pose_terms(stage, model, batch)["pose"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(head.parameters(), WARMUP_CLIP)
        opt.step()
        losses.append(float(loss.detach()))
    # The rest of the model got no gradient it should keep into the joint training.
    model.zero_grad(set_to_none=True)
    n = min(20, len(losses))
    return {
        "pose_warmup/first_loss": sum(losses[:n]) / n,
        "pose_warmup/last_loss": sum(losses[-n:]) / n,
    }
