"""A small standalone fitting loop for a tokenizer (tests, notebooks, quick experiments).

The project's training loop (``renderworld.training``) is the real trainer; this helper keeps
the tokenizer usable on its own: AdamW, optional per-step learning-rate multiplier, gradient
clipping, and a history of logged scalars.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable

import torch
from torch import nn

__all__ = ["fit"]


def fit(
    model: nn.Module,
    batches: Iterable[torch.Tensor],
    steps: int,
    lr: float = 1e-3,
    weight_decay: float = 0.01,
    grad_clip: float | None = 35.0,
    lr_scale: Callable[[int], float] | None = None,
    log_every: int = 1,
) -> list[dict[str, float]]:
    """Train ``model`` for ``steps`` optimizer steps on occupancy batches.

    Args:
        model: A module whose forward takes occupancy [B, X, Y, Z] and returns an object with a
            scalar ``loss`` and a ``logs`` dict (e.g. :class:`SceneTokenizer`).
        batches: Occupancy batches; cycled if shorter than ``steps``.
        steps: Number of optimizer steps (>= 1).
        lr: Base learning rate.
        weight_decay: AdamW weight decay.
        grad_clip: Max global gradient norm (None: no clipping).
        lr_scale: Optional ``step -> multiplier`` of ``lr`` (e.g. a warm-up or a spike).
        log_every: Record logs every this many steps (and at the last step).

    Returns:
        One dict per recorded step: ``step``, ``lr``, ``grad_norm`` and the model's logs.

    Raises:
        ValueError: on ``steps < 1``, ``lr <= 0`` or an empty ``batches``.
        FloatingPointError: when the loss or the gradient norm becomes non-finite (the step
            is not applied).
    """
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected a positive int, got {steps!r}")
    if not lr > 0:
        raise ValueError(f"lr: expected > 0, got {lr!r}")
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay)
    source = itertools.cycle(batches) if isinstance(batches, (list, tuple)) else iter(batches)
    history: list[dict[str, float]] = []
    model.train()
    for step in range(steps):
        try:
            occ = next(source)
        except StopIteration:
            if step == 0:
                raise ValueError("batches: expected at least one batch, got none") from None
            raise
        cur_lr = lr * (lr_scale(step) if lr_scale is not None else 1.0)
        for group in opt.param_groups:
            group["lr"] = cur_lr
        out = model(occ)
        if not torch.isfinite(out.loss):
            raise FloatingPointError(f"fit: non-finite loss {float(out.loss)} at step {step}")
        opt.zero_grad(set_to_none=True)
        out.loss.backward()
        max_norm = grad_clip if grad_clip is not None else math.inf
        grad_norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
        if not torch.isfinite(grad_norm):
            raise FloatingPointError(f"fit: non-finite gradient norm at step {step}")
        opt.step()
        if step % log_every == 0 or step == steps - 1:
            rec = {"step": float(step), "lr": cur_lr, "grad_norm": float(grad_norm)}
            rec.update({k: float(v) for k, v in out.logs.items()})
            history.append(rec)
    return history
