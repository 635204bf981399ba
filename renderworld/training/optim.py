"""Optimizer and learning-rate schedule from validated configs."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import torch
from torch import nn

from renderworld.training.config import OptimizerConfig, SchedulerConfig

__all__ = ["build_optimizer", "build_scheduler", "lr_multiplier", "default_param_groups"]


def default_param_groups(
    model: nn.Module, cfg: OptimizerConfig, lr_scales: Mapping[str, float] | None = None
) -> list[dict[str, Any]]:
    """Two groups: weight decay on >= 2-D parameters, none on biases and norm scales.

    With ``cfg.decay_1d_params`` every trainable parameter is decayed.

    Args:
        model: the model.
        cfg: the optimizer settings.
        lr_scales: parameter-name prefix -> factor on ``cfg.lr`` (e.g. ``{"pose.": 4.0}``): the
            parameters under each prefix get their own groups at ``cfg.lr * factor`` (the
            schedule multiplies every group's rate alike). None or empty: one rate.

    Raises:
        ValueError: no trainable parameter, a factor <= 0, or a prefix naming none.
    """
    params = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    if not params:
        raise ValueError(f"model: {type(model).__name__} has no trainable parameters")
    scales = dict(lr_scales or {})
    for prefix, factor in scales.items():
        if not factor > 0:
            raise ValueError(f"lr_scales[{prefix!r}]: expected a factor > 0, got {factor!r}")
        if not any(n.startswith(prefix) for n, _ in params):
            raise ValueError(f"lr_scales: prefix {prefix!r} names no trainable parameter")

    def scale_of(name: str) -> float:
        return next((f for pre, f in scales.items() if name.startswith(pre)), 1.0)

    groups = []
    for factor in sorted({scale_of(n) for n, _ in params}):
        mine = [(n, p) for n, p in params if scale_of(n) == factor]
        extra = {} if factor == 1.0 else {"lr": cfg.lr * factor}
        if cfg.decay_1d_params:
            groups.append({"params": [p for _, p in mine], "weight_decay": cfg.weight_decay})
            groups[-1].update(extra)
            continue
        decay = [p for _, p in mine if p.ndim >= 2]
        no_decay = [p for _, p in mine if p.ndim < 2]
        if decay:
            groups.append({"params": decay, "weight_decay": cfg.weight_decay, **extra})
        if no_decay:
            groups.append({"params": no_decay, "weight_decay": 0.0, **extra})
    return groups


def build_optimizer(
    model: nn.Module, cfg: OptimizerConfig, param_groups: Iterable[dict[str, Any]] | None = None
) -> torch.optim.Optimizer:
    """AdamW or SGD over ``param_groups`` (default: ``default_param_groups``)."""
    groups = list(param_groups) if param_groups is not None else default_param_groups(model, cfg)
    if cfg.name == "adamw":
        return torch.optim.AdamW(
            groups,
            lr=cfg.lr,
            betas=(cfg.betas[0], cfg.betas[1]),
            eps=cfg.eps,
            weight_decay=cfg.weight_decay,
        )
    if cfg.name == "sgd":
        return torch.optim.SGD(
            groups,
            lr=cfg.lr,
            momentum=cfg.momentum,
            nesterov=cfg.nesterov,
            weight_decay=cfg.weight_decay,
        )
    raise ValueError(f"optimizer.name: expected 'adamw' or 'sgd', got {cfg.name!r}")


def lr_multiplier(step: int, cfg: SchedulerConfig, total_steps: int) -> float:
    """Learning-rate factor applied after ``step`` completed optimizer steps.

    Warm-up: ``(step + 1) / (warmup_steps + 1)`` for ``step < warmup_steps`` (never zero, so
    the first step moves). Then cosine from 1 to ``min_lr_ratio`` over the remaining steps,
    or 1 for ``constant``.
    """
    w = cfg.warmup_steps
    if step < w:
        return (step + 1) / (w + 1)
    if cfg.name == "constant":
        return 1.0
    span = max(1, total_steps - w)
    progress = min(1.0, (step - w) / span)
    return cfg.min_lr_ratio + (1.0 - cfg.min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


def build_scheduler(
    optimizer: torch.optim.Optimizer, cfg: SchedulerConfig, total_steps: int
) -> torch.optim.lr_scheduler.LambdaLR:
    """A LambdaLR stepping once per optimizer step along ``lr_multiplier``.

    Its state_dict holds only numbers (the lambda is rebuilt from config on resume).
    """
    if total_steps < 1:
        raise ValueError(f"total_steps: expected >= 1, got {total_steps}")

    def factor(step: int) -> float:
        return lr_multiplier(step, cfg, total_steps)

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)
