"""Structured configs for the library-facing parts of training, validated at start.

The Hydra tree under ``configs/`` is free-form YAML; the groups that configure library objects
(``optimizer``, ``scheduler``, ``trainer``) are merged into the dataclasses below before a run
starts, so a typo'd key or a wrong type fails at once with a message naming the key, instead of
an hour into training. Stage configs stay free-form: each stage validates its own keys.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, TypeVar

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from renderworld.constants import GridSpec

__all__ = [
    "OptimizerConfig",
    "SchedulerConfig",
    "TrainerConfig",
    "validate_group",
    "grid_spec_from_config",
    "config_to_yaml",
]

T = TypeVar("T")

OPTIMIZERS = ("adamw", "sgd")
SCHEDULERS = ("cosine", "constant")
PRECISIONS = ("32", "bf16", "fp16")
MONITOR_MODES = ("min", "max")


@dataclass
class OptimizerConfig:
    """Optimizer settings (group ``optimizer``).

    Attributes:
        name: ``"adamw"`` or ``"sgd"``.
        lr: Peak learning rate (reached after warm-up).
        weight_decay: Decoupled weight decay (AdamW) or L2 (SGD).
        betas: AdamW betas.
        eps: AdamW epsilon.
        momentum: SGD momentum.
        nesterov: SGD Nesterov momentum.
        decay_1d_params: Also decay 1-D parameters (biases, norm scales). Off by default, as
            decaying them only pulls normalisation gains to zero.
    """

    name: str = "adamw"
    lr: float = 1e-3
    weight_decay: float = 0.01
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    eps: float = 1e-8
    momentum: float = 0.9
    nesterov: bool = False
    decay_1d_params: bool = False

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        _one_of("optimizer.name", self.name, OPTIMIZERS)
        _positive("optimizer.lr", self.lr)
        _non_negative("optimizer.weight_decay", self.weight_decay)
        if len(self.betas) != 2 or not all(0.0 <= b < 1.0 for b in self.betas):
            raise ValueError(f"optimizer.betas: expected two values in [0, 1), got {self.betas}")
        _positive("optimizer.eps", self.eps)
        _non_negative("optimizer.momentum", self.momentum)


@dataclass
class SchedulerConfig:
    """Learning-rate schedule over optimizer steps (group ``scheduler``).

    Linear warm-up from ``lr / (warmup_steps + 1)`` to ``lr`` over ``warmup_steps`` steps, then
    ``cosine`` decay to ``lr * min_lr_ratio`` at the last step, or ``constant``.

    Attributes:
        name: ``"cosine"`` or ``"constant"``.
        warmup_steps: Number of warm-up optimizer steps (0: none).
        min_lr_ratio: Final learning rate as a fraction of the peak (cosine only).
    """

    name: str = "cosine"
    warmup_steps: int = 0
    min_lr_ratio: float = 0.0

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        _one_of("scheduler.name", self.name, SCHEDULERS)
        _non_negative("scheduler.warmup_steps", self.warmup_steps)
        if not 0.0 <= self.min_lr_ratio <= 1.0:
            raise ValueError(
                f"scheduler.min_lr_ratio: expected a value in [0, 1], got {self.min_lr_ratio}"
            )


@dataclass
class TrainerConfig:
    """Loop settings (group ``trainer``). Steps are optimizer steps, not micro-batches.

    Attributes:
        max_steps: Stop after this many optimizer steps (None: use ``max_epochs``).
        max_epochs: Stop after this many passes over the training set (None: use ``max_steps``).
            With both set, whichever comes first.
        max_minutes: Wall-clock budget for training, summed over resumed segments; the run
            stops cleanly at the first step past it and writes ``last.pt``.
        batch_size: Samples per process per micro-batch. The global batch of one optimizer step
            is ``batch_size * grad_accum * world_size``.
        val_batch_size: Validation batch size per process (None: ``batch_size``).
        num_workers: DataLoader worker processes per training process.
        grad_accum: Micro-batches accumulated per optimizer step.
        grad_clip: Max global gradient L2 norm (None or 0: no clipping).
        ema_decay: Keep an exponential moving average of the weights with this decay in
            (0, 1) and validate, checkpoint (``model``) and read out the average; the trained
            weights are checkpointed as ``model_raw`` (:mod:`renderworld.training.ema`).
            None or 0: off.
        precision: ``"32"``, ``"bf16"`` or ``"fp16"`` (autocast on CUDA or CPU; fp16 with a
            gradient scaler). Networks run in it, geometry, rendering and losses in float32
            (:mod:`renderworld.precision`).
        device: ``"auto"`` (CUDA if available), ``"cpu"`` or ``"cuda"``.
        val_every: Validate every this many optimizer steps (None or 0: only at the end).
        log_every: Log training loss and throughput every this many optimizer steps.
        ckpt_every: Write ``last.pt`` every this many optimizer steps (None or 0: only at the
            end and when the time budget runs out).
        monitor: Validation metric that selects ``best.pt`` (None: no best checkpoint).
        monitor_mode: ``"min"`` or ``"max"``.
        progress_bar: Show a tqdm bar on rank 0.
        tensorboard: Also log to TensorBoard when it is installed.
        overfit_samples: Train and validate on the first N training samples (a debugging aid).
        deterministic: Ask torch for deterministic algorithms.
        num_threads: torch intra-op threads per process (None: torch's default).
        pin_memory: Pin host memory in the DataLoader (CUDA only).
        find_unused_parameters: Passed to DistributedDataParallel.
        data_seed: Seed of the training samples' order alone (None: the run's ``seed``), so
            the variance of a recipe can be split into its initialisation's and its data
            order's; everything else still follows ``seed``.
    """

    max_steps: int | None = 1000
    max_epochs: int | None = None
    max_minutes: float | None = None
    batch_size: int = 1
    val_batch_size: int | None = None
    num_workers: int = 0
    grad_accum: int = 1
    grad_clip: float | None = 1.0
    ema_decay: float | None = None
    precision: str = "32"
    device: str = "auto"
    val_every: int | None = 500
    log_every: int = 50
    ckpt_every: int | None = 500
    monitor: str | None = "val/loss"
    monitor_mode: str = "min"
    progress_bar: bool = True
    tensorboard: bool = True
    overfit_samples: int | None = None
    deterministic: bool = False
    num_threads: int | None = None
    pin_memory: bool = False
    find_unused_parameters: bool = False
    data_seed: int | None = None

    def validate(self) -> None:
        """Raise ValueError naming the first invalid field."""
        if self.max_steps is None and self.max_epochs is None:
            raise ValueError("trainer: set max_steps or max_epochs (both are None)")
        for key in ("max_steps", "max_epochs", "batch_size", "grad_accum", "log_every"):
            value = getattr(self, key)
            if value is not None:
                _positive(f"trainer.{key}", value)
        for key in ("val_batch_size", "overfit_samples", "num_threads"):
            value = getattr(self, key)
            if value is not None:
                _positive(f"trainer.{key}", value)
        for key in ("num_workers", "val_every", "ckpt_every"):
            value = getattr(self, key)
            if value is not None:
                _non_negative(f"trainer.{key}", value)
        if self.max_minutes is not None:
            _positive("trainer.max_minutes", self.max_minutes)
        if self.data_seed is not None and (
            isinstance(self.data_seed, bool)
            or not isinstance(self.data_seed, int)
            or not 0 <= self.data_seed < 2**31
        ):
            raise ValueError(
                f"trainer.data_seed: expected null or an int in [0, 2**31), got {self.data_seed!r}"
            )
        if self.grad_clip is not None:
            _non_negative("trainer.grad_clip", self.grad_clip)
        if self.ema_decay and not 0.0 < self.ema_decay < 1.0:
            raise ValueError(
                f"trainer.ema_decay: expected a value in (0, 1) (or null: off), got "
                f"{self.ema_decay}"
            )
        _one_of("trainer.precision", self.precision, PRECISIONS)
        _one_of("trainer.monitor_mode", self.monitor_mode, MONITOR_MODES)
        if self.device not in ("auto", "cpu") and not self.device.startswith("cuda"):
            raise ValueError(
                f"trainer.device: expected 'auto', 'cpu' or 'cuda[:i]', got {self.device!r}"
            )


def validate_group(node: Any, schema: type[T], group: str) -> T:
    """Merge a config group into its dataclass schema and validate it.

    Args:
        node: The group's config (DictConfig or dict), e.g. ``cfg.trainer``.
        schema: The dataclass (``TrainerConfig``...).
        group: Group name used in error messages.

    Returns:
        A validated instance of ``schema``.

    Raises:
        ValueError: unknown key, wrong type or out-of-range value; the message names the key.
    """
    if node is None:
        raise ValueError(f"{group}: the config group is missing (got None)")
    if not isinstance(node, (DictConfig, dict)):
        raise TypeError(f"{group}: expected a mapping, got {type(node).__name__}")
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), node)
        obj = OmegaConf.to_object(merged)
    except OmegaConfBaseException as err:
        msg = str(err).splitlines()[0]
        key = getattr(err, "full_key", None)
        raise ValueError(f"{group}.{key}: {msg}" if key else f"{group}: {msg}") from None
    obj.validate()  # type: ignore[attr-defined]
    return obj  # type: ignore[return-value]


def grid_spec_from_config(node: Any) -> GridSpec:
    """Build a ``GridSpec`` from a ``grid`` config group (name, range_min, range_max, shape).

    Raises:
        ValueError: missing key, wrong length or a non-positive extent.
    """
    try:
        name = str(node["name"])
        lo = tuple(float(v) for v in node["range_min"])
        hi = tuple(float(v) for v in node["range_max"])
        shape = tuple(int(v) for v in node["shape"])
    except (KeyError, TypeError) as err:
        raise ValueError(
            f"grid: expected keys name, range_min, range_max, shape; got {node!r} ({err})"
        ) from None
    if len(lo) != 3 or len(hi) != 3 or len(shape) != 3:
        raise ValueError(f"grid {name!r}: range_min, range_max and shape need 3 values each")
    if any(h <= low for low, h in zip(lo, hi)) or any(n <= 0 for n in shape):
        raise ValueError(f"grid {name!r}: need range_max > range_min and shape > 0, got {node!r}")
    return GridSpec(name, lo, hi, shape)  # type: ignore[arg-type]


def config_to_yaml(cfg: Any) -> str:
    """Resolve a config and return it as YAML text (what checkpoints and run dirs store)."""
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_yaml(cfg, resolve=True)
    return OmegaConf.to_yaml(OmegaConf.create(cfg), resolve=True)


def _one_of(key: str, value: Any, options: tuple[str, ...]) -> None:
    if value not in options:
        raise ValueError(f"{key}: expected one of {list(options)}, got {value!r}")


def _positive(key: str, value: float) -> None:
    if not value > 0:
        raise ValueError(f"{key}: expected a positive value, got {value!r}")


def _non_negative(key: str, value: float) -> None:
    if not value >= 0:
        raise ValueError(f"{key}: expected a non-negative value, got {value!r}")
