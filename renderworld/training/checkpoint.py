"""Checkpoints: atomic writes, weights-only strict loads, clear errors.

A checkpoint is a dict of tensors, dicts, lists and primitives only, so it loads with
``torch.load(weights_only=True)`` (no code runs on load). Layout (schema version 1)::

    schema_version  int       CHECKPOINT_SCHEMA_VERSION
    stage           str       registered stage name
    step            int       optimizer steps done
    epoch           int       current epoch
    samples_in_epoch int      samples of this epoch already consumed, all ranks together
    elapsed_s       float     training wall time so far, summed over resumed segments
    world_size      int
    config          str       the resolved run config, YAML
    model           dict      state_dict of the unwrapped model
    optimizer, scheduler, grad_scaler   dict  their state_dicts ({} when unused)
    rng             list      per-rank RNG states (seed.get_rng_state)
    best            dict      {"metric": str|None, "value": float|None, "step": int|None}
    metrics         dict      last validation metrics {name: float}

This module imports neither Hydra nor OmegaConf: the planner API can load weights without them.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

__all__ = [
    "CHECKPOINT_SCHEMA_VERSION",
    "CheckpointError",
    "save_checkpoint",
    "load_checkpoint",
    "load_model_weights",
    "check_state_dict_keys",
]

CHECKPOINT_SCHEMA_VERSION = 1
REQUIRED_KEYS = ("schema_version", "stage", "step", "config", "model")
TRAINING_KEYS = ("optimizer", "scheduler", "rng", "epoch", "samples_in_epoch")
_MAX_LISTED = 20


class CheckpointError(ValueError):
    """A checkpoint cannot be used: unreadable, wrong stage, wrong schema, mismatched keys."""


def save_checkpoint(state: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """Write ``state`` to ``path`` atomically.

    The data goes to a temporary file in the same directory, is flushed and fsynced, then
    ``os.replace``-d over ``path`` and the directory is fsynced: a crash at any moment leaves
    either the old file or the new one, never a torn one.

    Args:
        state: Checkpoint dict (must carry ``schema_version`` and ``stage``).
        path: Destination file; its directory is created.

    Returns:
        The destination path.
    """
    if not isinstance(state, Mapping):
        raise TypeError(f"state: expected a mapping, got {type(state).__name__}")
    for key in ("schema_version", "stage"):
        if key not in state:
            raise ValueError(f"state: a checkpoint needs {key!r}; keys: {sorted(state)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # Same directory (os.replace is atomic only within a filesystem); "x" mode respects umask.
    tmp = path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    try:
        with open(tmp, "xb") as f:
            torch.save(dict(state), f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def load_checkpoint(
    path: str | os.PathLike,
    expected_stage: str | None = None,
    *,
    for_training: bool = False,
) -> dict[str, Any]:
    """Load and validate a checkpoint (``torch.load(weights_only=True)``, on CPU).

    Args:
        path: Checkpoint file.
        expected_stage: If given, the stage that must have written it.
        for_training: Also require the optimizer, scheduler, RNG and sampler state.

    Returns:
        The checkpoint dict (see the module docstring).

    Raises:
        CheckpointError: missing, truncated or corrupt file, non-weights-only content, another
            schema version, another stage, missing entries. The message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r}: no such file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises several types for torn zips and bad pickles
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        hint = (
            "it holds objects other than tensors/containers/primitives"
            if "weights_only" in str(err).lower() or "weights only" in str(err).lower()
            else "the file is truncated or corrupt (an interrupted copy?)"
        )
        raise CheckpointError(
            f"checkpoint {str(path)!r} cannot be read: {hint} [{type(err).__name__}: {first}]"
        ) from err
    if not isinstance(ckpt, dict):
        raise CheckpointError(
            f"checkpoint {str(path)!r}: expected a dict, got {type(ckpt).__name__} "
            "(a bare state_dict or another tool's file?)"
        )
    version = ckpt.get("schema_version")
    if version != CHECKPOINT_SCHEMA_VERSION:
        raise CheckpointError(
            f"checkpoint {str(path)!r}: schema version {version!r}, this RenderWorld reads "
            f"version {CHECKPOINT_SCHEMA_VERSION}"
        )
    required = REQUIRED_KEYS + (TRAINING_KEYS if for_training else ())
    missing = [k for k in required if k not in ckpt]
    if missing:
        raise CheckpointError(f"checkpoint {str(path)!r}: missing entries {missing}")
    if expected_stage is not None and ckpt["stage"] != expected_stage:
        raise CheckpointError(
            f"checkpoint {str(path)!r} was written by stage {ckpt['stage']!r}, "
            f"expected stage {expected_stage!r}"
        )
    return ckpt


def check_state_dict_keys(
    model: nn.Module, state_dict: Mapping[str, torch.Tensor], source: str = "checkpoint"
) -> None:
    """Raise unless ``state_dict`` has exactly the model's keys and shapes.

    Keys listed in the model's ``optional_state_keys`` attribute may be missing (the model
    gives them defaults on load, e.g. readout calibration added after a checkpoint was written).

    Raises:
        CheckpointError: listing missing keys, unexpected keys and shape mismatches.
    """
    own = model.state_dict()
    # Keys a model fills in itself when an older checkpoint lacks them (its load pre-hook).
    optional = set(getattr(model, "optional_state_keys", ()))
    missing = sorted(set(own) - set(state_dict) - optional)
    unexpected = sorted(set(state_dict) - set(own))
    shapes = sorted(
        f"{k}: model {tuple(own[k].shape)} vs checkpoint {tuple(state_dict[k].shape)}"
        for k in set(own) & set(state_dict)
        if isinstance(state_dict[k], torch.Tensor) and own[k].shape != state_dict[k].shape
    )
    if missing or unexpected or shapes:
        parts = []
        for label, items in (
            ("missing keys", missing),
            ("unexpected keys", unexpected),
            ("shape mismatches", shapes),
        ):
            if items:
                shown = ", ".join(items[:_MAX_LISTED])
                extra = len(items) - _MAX_LISTED
                more = f" ... (+{extra} more)" if extra > 0 else ""
                parts.append(f"{label} ({len(items)}): {shown}{more}")
        raise CheckpointError(
            f"{source} does not match the model {type(model).__name__}: " + "; ".join(parts)
        )


def load_model_weights(
    model: nn.Module, path: str | os.PathLike, expected_stage: str | None = None
) -> dict[str, Any]:
    """Load a checkpoint's model weights into ``model`` strictly.

    Args:
        model: The model to fill (any device; tensors are copied to it).
        path: Checkpoint file.
        expected_stage: If given, the stage that must have written it.

    Returns:
        The checkpoint dict (step, config, metrics...).

    Raises:
        CheckpointError: see ``load_checkpoint`` and ``check_state_dict_keys``.
    """
    if not isinstance(model, nn.Module):
        raise TypeError(f"model: expected a torch.nn.Module, got {type(model).__name__}")
    ckpt = load_checkpoint(path, expected_stage)
    check_state_dict_keys(model, ckpt["model"], source=f"checkpoint {str(path)!r}")
    model.load_state_dict(ckpt["model"], strict=True)
    return ckpt


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # platforms without directory fds
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
