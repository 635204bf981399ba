"""Stages: what a training stage provides, and the registry that finds one by name.

A stage (Img2Occ, tokenizer, world model...) is a small class that builds its model, datasets,
loss and metrics from the config; the loop in ``loop.py`` does everything else. Stages register
themselves with ``@register_stage("name")`` in their own sub-package. The loop never imports a
stage it does not run: ``get_stage`` imports the module named by the stage config's
``_target_module_`` on first use, which registers the class.

Metrics and ranks: ``evaluate`` returns *additive statistics* (sums, counts, confusion
matrices) as tensors; the loop sums them over ranks and only then calls ``compute_metrics``, so a
metric over a sharded validation set equals the single-process one (sum of sums, not a mean of
means).
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Mapping
from typing import Any

import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

__all__ = ["Stage", "register_stage", "get_stage", "registered_stages", "sum_count"]

_REGISTRY: dict[str, type[Stage]] = {}


class Stage(ABC):
    """Base class of a training stage.

    Subclasses implement the four abstract methods; the hooks have working defaults.
    The instance is built once per run with the full (resolved) config and keeps it in
    ``self.cfg``.

    Attributes:
        name: Registered name, set by ``register_stage``.
        cfg: The full run config.
    """

    name: str = ""

    def __init__(self, cfg: Any) -> None:
        self.cfg = cfg

    @abstractmethod
    def build_model(self, cfg: Any) -> nn.Module:
        """Return the model to train, on CPU; the loop moves it to the device."""

    @abstractmethod
    def build_datasets(self, cfg: Any) -> tuple[Dataset, Dataset | None]:
        """Return ``(train, val)`` map-style datasets; ``val`` may be None."""

    def build_val_dataset(self, cfg: Any) -> Dataset | None:
        """The validation dataset alone (what ``tools/eval.py`` reads); by default the second
        of :meth:`build_datasets`. Override when the train split need not exist to evaluate."""
        return self.build_datasets(cfg)[1]

    @abstractmethod
    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, Mapping[str, Any]]:
        """Return ``(loss, logs)`` for one micro-batch already on the model's device.

        ``loss`` is a scalar tensor, the mean over the batch (the loop divides by the number of
        accumulation steps). ``logs`` maps names to scalars (floats or 0-d tensors) to log.
        ``model`` may be wrapped in DistributedDataParallel: call it, don't reach inside.
        """

    @abstractmethod
    def evaluate(self, model: nn.Module, loader: DataLoader) -> dict[str, torch.Tensor]:
        """Return additive statistics over ``loader`` (this rank's shard).

        Called under ``torch.no_grad()`` with the model in eval mode. Values are float tensors
        that may be summed across ranks: sums and counts (see ``sum_count``), confusion
        matrices... ``compute_metrics`` turns the summed statistics into metrics. Every rank
        must return the same keys and shapes, also for an empty shard (zeros).
        """

    # ---------------------------------------------------------------- optional hooks
    def compute_metrics(self, stats: Mapping[str, torch.Tensor]) -> dict[str, float]:
        """Turn rank-summed statistics into metrics.

        The default understands pairs ``"<m>/sum"`` and ``"<m>/count"`` and returns
        ``{"<m>": sum / count}``; override it for anything else (e.g. IoU from a confusion).

        Raises:
            ValueError: a statistic without its partner.
        """
        metrics: dict[str, float] = {}
        for key in stats:
            if key.endswith("/sum"):
                base = key[: -len("/sum")]
                if f"{base}/count" not in stats:
                    raise ValueError(f"stats: {key!r} has no matching {base + '/count'!r}")
                count = float(stats[f"{base}/count"])
                metrics[base] = float(stats[key]) / count if count > 0 else float("nan")
            elif key.endswith("/count"):
                if f"{key[: -len('/count')]}/sum" not in stats:
                    raise ValueError(f"stats: {key!r} has no matching '/sum' statistic")
            else:
                raise ValueError(
                    f"stats: cannot reduce {key!r} by default; name statistics '<m>/sum' and "
                    f"'<m>/count' or override {type(self).__name__}.compute_metrics"
                )
        return metrics

    def collate_fn(self) -> Callable[[list[Any]], Any] | None:
        """DataLoader collate function (None: torch's default)."""
        return None

    def transfer_batch(self, batch: Any, device: torch.device) -> Any:
        """Move a batch to ``device``; the default handles tensors in dicts, lists, tuples."""
        return _to_device(batch, device)

    def param_groups(self, model: nn.Module) -> Iterable[dict[str, Any]] | None:
        """Optimizer parameter groups (None: the loop's decay / no-decay split)."""
        return None

    def lr_scales(self) -> Mapping[str, float]:
        """Parameter-name prefix -> factor on the learning rate, for the loop's default groups
        (``renderworld.training.optim.default_param_groups``); empty: one rate."""
        return {}

    def warm_start(self, model: nn.Module) -> None:  # noqa: B027 - optional
        """Called once before the first step of a fresh run, never on a resume (its result is
        in the checkpoints): e.g. fit one part of the model alone first. The loop isolates the
        global RNGs around it, so the run's own random stream is the same with or without it."""

    def on_train_start(self, model: nn.Module, run_dir: str) -> None:  # noqa: B027 - optional
        """Called once before the first step (also after a resume)."""

    def on_train_end(  # noqa: B027 - optional
        self, model: nn.Module, run_dir: str
    ) -> Mapping[str, float] | None:
        """Called on every rank after the last step and the final checkpoint.

        Returns:
            Validation metrics of the final weights that replace the loop's last ones in what
            ``train`` returns and logs (e.g. scored with a readout chosen here), or None.
        """

    def on_eval_start(self, model: nn.Module) -> None:  # noqa: B027 - optional
        """Called by ``evaluate(cfg)`` on every rank once the checkpoint's weights are loaded,
        before scoring: e.g. re-fit a calibration of those weights that the config asks for."""

    def on_eval_end(  # noqa: B027 - optional
        self, model: nn.Module, metrics: Mapping[str, float], run_dir: str
    ) -> None:
        """Called by ``evaluate(cfg)`` on rank 0 after ``eval_metrics.json`` is written.

        For extra outputs in the eval run directory (pictures, tables). ``model`` holds the
        checkpoint's weights, on the evaluation device; ``metrics`` are the returned ones.
        """

    def write_report(self, metrics: Mapping[str, float], run_dir: str) -> str | None:
        """Write human-readable reports of final metrics into ``run_dir``; rank 0 only.

        Called by ``evaluate(cfg)`` after ``eval_metrics.json`` and by ``train(cfg)`` after the
        last validation, with their returned metrics (``val/``-prefixed). Returns text for the
        entry point to print (e.g. a results table), or None (the default: no report).
        """
        return None


def register_stage(name: str) -> Callable[[type[Stage]], type[Stage]]:
    """Class decorator registering a ``Stage`` subclass under ``name``.

    Raises:
        TypeError: the class is not a Stage subclass.
        ValueError: ``name`` is empty or already taken by another class.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name: expected a non-empty string, got {name!r}")

    def decorator(cls: type[Stage]) -> type[Stage]:
        if not (isinstance(cls, type) and issubclass(cls, Stage)):
            raise TypeError(f"register_stage({name!r}): expected a Stage subclass, got {cls!r}")
        other = _REGISTRY.get(name)
        if other is not None and other.__qualname__ != cls.__qualname__:
            raise ValueError(
                f"register_stage: name {name!r} is already registered to "
                f"{other.__module__}.{other.__qualname__}"
            )
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return decorator


def get_stage(name: str, module: str | None = None) -> type[Stage]:
    """Return the stage class registered as ``name``, importing ``module`` first if needed.

    Args:
        name: Registered stage name (``cfg.stage.name``).
        module: Import path of the module that registers it (``cfg.stage._target_module_``).

    Raises:
        ValueError: the module cannot be imported or does not register ``name``.
    """
    if name not in _REGISTRY and module:
        try:
            importlib.import_module(module)
        except ImportError as err:
            raise ValueError(
                f"stage {name!r}: cannot import its module {module!r} "
                f"(stage._target_module_): {err}"
            ) from err
    if name not in _REGISTRY:
        where = f"module {module!r} does not register it" if module else "no module given"
        raise ValueError(
            f"stage {name!r} is not registered ({where}); registered: {sorted(_REGISTRY)}. "
            "Set stage._target_module_ to the module defining @register_stage"
            f"({name!r})."
        )
    return _REGISTRY[name]


def registered_stages() -> list[str]:
    """Names of the stages registered so far (imported modules only)."""
    return sorted(_REGISTRY)


def sum_count(name: str, values: torch.Tensor) -> dict[str, torch.Tensor]:
    """Statistics for a mean metric: ``{"<name>/sum": sum, "<name>/count": numel}`` (float64).

    Args:
        name: Metric name.
        values: Per-sample values, any shape.
    """
    values = values.detach()
    return {
        f"{name}/sum": values.sum().to(torch.float64).cpu(),
        f"{name}/count": torch.tensor(float(values.numel()), dtype=torch.float64),
    }


def _to_device(batch: Any, device: torch.device) -> Any:
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, Mapping):
        return {k: _to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, tuple) and hasattr(batch, "_fields"):  # namedtuple
        return type(batch)(*(_to_device(v, device) for v in batch))
    if isinstance(batch, (list, tuple)):
        return type(batch)(_to_device(v, device) for v in batch)
    return batch
