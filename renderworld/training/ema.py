"""Exponential moving average of the weights, for validation, checkpoints and readout.

With batch size 1 the weights after the last optimizer step carry that step's noise; the
average over the last ~1 / (1 - decay) steps does not. The averaging itself is
``torch.optim.swa_utils.AveragedModel`` with ``get_ema_multi_avg_fn`` (the first update copies
the weights, later ones blend ``avg <- decay * avg + (1 - decay) * w``). Buffers are not
averaged: they are copied from the trained model at every update, so buffers a stage changes
on purpose (thresholds, codebook statistics) are the trained model's.

Checkpoint layout with an EMA (see :class:`renderworld.training.loop.Trainer`): ``model`` holds
the averaged weights (what evaluation, export and the threshold search load), ``model_raw`` the
weights the optimizer steps, ``ema`` ``{"decay", "n_averaged"}``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

__all__ = ["WeightEMA"]


class WeightEMA:
    """EMA copy of a model's parameters.

    Args:
        model: The trained model (not DDP-wrapped); deep-copied once.
        decay: Weight of the old average per update, in (0, 1); 0.998 averages over roughly
            the last 500 optimizer steps.

    Raises:
        ValueError: ``decay`` outside (0, 1).
    """

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0.0 < float(decay) < 1.0:
            raise ValueError(f"trainer.ema_decay: expected a value in (0, 1), got {decay}")
        self.decay = float(decay)
        self.averaged = AveragedModel(
            model, multi_avg_fn=get_ema_multi_avg_fn(self.decay), use_buffers=False
        )
        self.averaged.eval()

    @property
    def module(self) -> nn.Module:
        """The averaged model (same class and state-dict keys as the trained one)."""
        return self.averaged.module

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Blend ``model``'s parameters into the average; copy its buffers."""
        self.averaged.update_parameters(model)
        for avg, live in zip(self.module.buffers(), model.buffers(), strict=True):
            avg.copy_(live)

    def state(self) -> dict[str, Any]:
        """``{"decay", "n_averaged"}`` for the checkpoint (the weights go in ``model``)."""
        return {"decay": self.decay, "n_averaged": int(self.averaged.n_averaged)}

    def load(self, weights: dict[str, torch.Tensor], state: dict[str, Any] | None) -> None:
        """Restore the average from a checkpoint's ``model`` entry and ``ema`` record.

        Args:
            weights: State dict of the averaged model (strict keys).
            state: The checkpoint's ``ema`` record; None (a checkpoint written without an EMA)
                restarts the average: the next update copies the trained weights.
        """
        self.module.load_state_dict(weights, strict=True)
        n = int(state["n_averaged"]) if state else 0
        self.averaged.n_averaged.fill_(n)
