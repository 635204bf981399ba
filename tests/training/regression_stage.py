"""A small real stage for testing the loop: fit ``y = A x + b + noise`` with a linear model.

The data are fixed by ``stage.data_seed``; the optimum validation MSE is about ``noise**2``, so a
test can assert that the loop actually learns.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.utils.data import Dataset

from renderworld.training.registry import Stage, register_stage, sum_count

__all__ = ["RegressionStage", "RegressionData"]


class RegressionData(Dataset):
    """``n`` pairs ``(x [D], y [K])`` with ``y = A x + b + noise * eps``.

    ``jitter > 0`` adds fresh Gaussian noise to ``x`` on every access (an "augmentation" that
    draws from the global torch RNG).
    """

    def __init__(self, a: torch.Tensor, b: torch.Tensor, n: int, noise: float, seed: int,
                 jitter: float = 0.0) -> None:  # fmt: skip
        gen = torch.Generator().manual_seed(seed)
        self.x = torch.randn(n, a.shape[1], generator=gen)
        self.y = self.x @ a.T + b + noise * torch.randn(n, a.shape[0], generator=gen)
        self.jitter = jitter

    def __len__(self) -> int:
        return len(self.x)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        x = self.x[i]
        if self.jitter > 0:
            x = x + self.jitter * torch.randn_like(x)
        return {"x": x, "y": self.y[i]}


@register_stage("regression")
class RegressionStage(Stage):
    """Linear regression with optional input dropout."""

    def build_model(self, cfg: Any) -> nn.Module:
        s = cfg.stage
        return nn.Sequential(nn.Dropout(float(s.dropout)), nn.Linear(s.in_features, s.out_features))

    def build_datasets(self, cfg: Any) -> tuple[Dataset, Dataset]:
        s = cfg.stage
        gen = torch.Generator().manual_seed(int(s.data_seed))
        a = torch.randn(s.out_features, s.in_features, generator=gen)
        b = torch.randn(s.out_features, generator=gen)
        seed = int(s.data_seed)
        train = RegressionData(a, b, s.num_train, s.noise, seed + 1, float(s.jitter))
        val = RegressionData(a, b, s.num_val, s.noise, seed + 2)
        return train, val

    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, Any]]:
        s = self.cfg.stage
        self.calls = getattr(self, "calls", 0) + 1
        if s.step_sleep:
            time.sleep(float(s.step_sleep))
        if s.crash_at_call is not None and self.calls == s.crash_at_call:
            raise RuntimeError(f"simulated crash at loss call {self.calls}")
        err = model(batch["x"]) - batch["y"]
        mse = err.pow(2).mean()
        if s.nan_at_call is not None and self.calls == s.nan_at_call:
            mse = mse * float("nan")
        return mse, {"mae": err.abs().mean()}

    def evaluate(self, model: nn.Module, loader: Any) -> dict[str, torch.Tensor]:
        stats: dict[str, torch.Tensor] = {}
        for batch in loader:
            err = model(batch["x"].to(next(model.parameters()).device)) - batch["y"].to(
                next(model.parameters()).device
            )
            for k, v in {
                **sum_count("loss", err.pow(2).mean(dim=1)),
                **sum_count("mae", err.abs().mean(dim=1)),
            }.items():
                stats[k] = stats.get(k, 0) + v
        return stats

    def on_train_end(self, model: nn.Module, run_dir: str) -> None:
        if self.cfg.stage.dump_params:
            rank = torch.distributed.get_rank() if torch.distributed.is_initialized() else 0
            state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
            torch.save(state, Path(run_dir) / f"params_rank{rank}.pt")
