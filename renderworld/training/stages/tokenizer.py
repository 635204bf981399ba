"""The ``tokenizer`` stage: train AM-VAE / VQ-VAE variants on occupancy frames.

Data: single keyframes of ``OccSequenceDataset`` (history 1, future 0) on the run's grid, from
the dataset's Occ3D gts or from exported pseudo labels (``stage.occ_root``). Metrics:
reconstruction mIoU over classes 0..16 and occupied-vs-free IoU on the full volume (OccWorld
protocol), and the same inside the camera mask (``cam/`` prefix), from confusions summed over
the split (and over ranks).
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import OmegaConf
from torch import nn
from torch.utils.data import Dataset

from renderworld.data import OccSequenceDataset, load_infos
from renderworld.tokenizer import SceneTokenizer, TokenizerConfig, build_tokenizer
from renderworld.training.checkpoint import load_checkpoint
from renderworld.training.registry import Stage, register_stage
from renderworld.training.stages.common import (
    confusion_stats,
    evaluated_checkpoint,
    grid_of,
    infos_dir,
    occupancy_metrics,
    warn_architecture_differs,
)

__all__ = [
    "PRIOR_FRAMES",
    "TokenizerStage",
    "balanced_class_weights",
    "OccFrames",
    "tokenizer_config",
    "load_tokenizer",
]

#: Training frames whose class frequencies start the output heads (``stage.prior_init``).
PRIOR_FRAMES = 64


class OccFrames(Dataset):
    """Single occupancy frames: ``{"occ": uint8 [X,Y,Z], "mask_camera": bool [X,Y,Z]}``."""

    def __init__(self, infos, data_root, grid, occ_root=None):
        self.seq = OccSequenceDataset(
            infos, data_root, history=1, future=0, grid=grid, occ_root=occ_root
        )

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        item = self.seq[i]
        return {"occ": item["occ"][0], "mask_camera": item["mask_camera"][0]}


def tokenizer_config(cfg: Any) -> TokenizerConfig:
    """The :class:`TokenizerConfig` of a run config (``stage.model`` on the run's grid)."""
    grid = grid_of(cfg)
    model = OmegaConf.to_container(cfg.stage.model, resolve=True) if cfg.stage.model else {}
    latent = model.pop("latent_shape", None)
    if latent is None:
        f = next(f for f in (4, 2, 1) if grid.shape[0] % f == 0 and grid.shape[1] % f == 0)
        latent = (grid.shape[0] // f, grid.shape[1] // f)
    return TokenizerConfig(grid_shape=tuple(grid.shape), latent_shape=tuple(latent), **model)


def load_tokenizer(path, device: str | torch.device = "cpu") -> SceneTokenizer:
    """Rebuild a trained tokenizer from a ``tokenizer`` checkpoint, frozen, in eval mode.

    Args:
        path: ``last.pt`` / ``best.pt`` written by ``tools/train.py stage=tokenizer``.
        device: where to put it.

    Raises:
        CheckpointError: when the file is not a tokenizer checkpoint or its weights do not fit.
    """
    from renderworld.training.checkpoint import check_state_dict_keys

    ckpt = load_checkpoint(path, expected_stage="tokenizer")
    model = build_tokenizer(tokenizer_config(OmegaConf.create(ckpt["config"])))
    check_state_dict_keys(model, ckpt["model"], str(path))
    model.load_state_dict(ckpt["model"], strict=True)
    model.to(device).eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def balanced_class_weights(counts: torch.Tensor, power: float) -> torch.Tensor:
    """Cross-entropy weights from class frequencies: ``(f_c / max_c f_c) ** -power``.

    The most frequent class weighs 1; a class that never occurs gets the largest weight of the
    classes that do (it has no voxel to weigh, and a rare class is not out-weighed by it).

    Args:
        counts: [18] voxel counts per Occ3D class.
        power: p >= 0; 0 gives equal weights, 0.5 the inverse square root of the frequency.

    Returns:
        [18] float32 weights, each >= 1.

    Raises:
        ValueError: naming ``counts`` (not 18, or all zero) or ``power`` (negative).
    """
    counts = torch.as_tensor(counts, dtype=torch.float64)
    seen = counts > 0
    if counts.shape != (18,) or not bool(seen.any()):
        raise ValueError(f"counts: expected [18] counts with one > 0, got {counts.tolist()}")
    if power < 0:
        raise ValueError(f"power: expected a number >= 0, got {power}")
    w = torch.ones(18, dtype=torch.float64)
    w[seen] = (counts[seen] / counts.max()) ** -power
    w[~seen] = w[seen].max()
    return w.float()


@register_stage("tokenizer")
class TokenizerStage(Stage):
    """Scene tokenizer training (variant from ``stage.model.variant``)."""

    def __init__(self, cfg: Any) -> None:
        super().__init__(cfg)
        prior = cfg.stage.get("prior_init", False)
        if not isinstance(prior, bool):
            raise ValueError(f"stage.prior_init: expected true or false, got {prior!r}")
        self.prior_init = prior
        balance = cfg.stage.get("class_balance", 0.0)
        if isinstance(balance, bool) or not isinstance(balance, (int, float)) or balance < 0:
            raise ValueError(f"stage.class_balance: expected a number >= 0, got {balance!r}")
        self.class_balance = float(balance)
        if self.class_balance > 0 and (cfg.stage.get("model") or {}).get("class_weights"):
            raise ValueError(
                "stage.class_balance: set either it or stage.model.class_weights, not both"
            )
        self._train_set: Dataset | None = None
        self._counts: torch.Tensor | None = None  # _frame_counts of _train_set, read once

    def build_model(self, cfg: Any) -> nn.Module:
        """The tokenizer; when evaluating (``ckpt`` set) its architecture is the checkpoint's,
        so a checkpoint trained before a default changed still evaluates (a warning names what
        differs from the run's ``stage.model``).

        Raises:
            ValueError: naming ``ckpt`` when the checkpoint's grid is not the run's.
        """
        mine = tokenizer_config(cfg)
        ckpt = evaluated_checkpoint(cfg)
        if ckpt is None:
            return build_tokenizer(mine)
        stored = load_checkpoint(ckpt, expected_stage="tokenizer")["config"]
        theirs = tokenizer_config(OmegaConf.create(stored))
        if theirs.grid_shape != mine.grid_shape:
            raise ValueError(
                f"ckpt: {str(ckpt)!r} was trained on a {theirs.grid_shape} grid, the run's is "
                f"{mine.grid_shape} (grid=...)"
            )
        warn_architecture_differs(ckpt, theirs, mine)
        return build_tokenizer(theirs)

    def build_datasets(self, cfg: Any) -> tuple[Dataset, Dataset | None]:
        folder = infos_dir(cfg)
        grid, occ_root = grid_of(cfg), cfg.stage.get("occ_root")
        root = str(cfg.dataset.data_root)
        train = OccFrames(load_infos(folder, cfg.dataset.train_split), root, grid, occ_root)
        val = OccFrames(load_infos(folder, cfg.dataset.val_split), root, grid, occ_root)
        self._train_set, self._counts = train, None
        return train, val

    def _frame_counts(self, z: int) -> torch.Tensor:
        """[Z, 18] voxel counts per height level and class of up to :data:`PRIOR_FRAMES`
        evenly spaced training frames."""
        if self._counts is not None and self._counts.shape[0] == z:
            return self._counts
        if self._train_set is None:
            raise RuntimeError("tokenizer stage: no training frames (call build_datasets first)")
        n = len(self._train_set)
        pick = sorted({round(i * (n - 1) / max(PRIOR_FRAMES - 1, 1)) for i in range(PRIOR_FRAMES)})
        counts = torch.zeros(z, 18, dtype=torch.float64)
        for i in pick[:n]:
            occ = self._train_set[i]["occ"].long()  # [X, Y, Z]
            for level in range(z):
                counts[level] += torch.bincount(occ[..., level].reshape(-1), minlength=18).double()
        self._counts = counts
        return counts

    def warm_start(self, model: nn.Module) -> None:
        """``stage.prior_init``: start the output heads at the training frames' class
        frequencies (:meth:`~renderworld.tokenizer.SceneTokenizer.init_output_prior`)."""
        if not self.prior_init:
            return
        raw = model.module if hasattr(model, "module") else model
        raw.init_output_prior(self._frame_counts(raw.cfg.grid_shape[2]))

    def on_train_start(self, model: nn.Module, run_dir: str) -> None:
        """``stage.class_balance`` p > 0: weight each voxel's cross-entropy by its true class's
        training frequency to the power -p (:func:`balanced_class_weights`); set on every start,
        resumes included (the weights are not part of the checkpoint)."""
        if self.class_balance == 0.0:
            return
        raw = model.module if hasattr(model, "module") else model
        counts = self._frame_counts(raw.cfg.grid_shape[2]).sum(0)
        raw.class_weights = balanced_class_weights(counts, self.class_balance).to(
            next(raw.parameters()).device
        )

    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, Any]]:
        out = model(batch["occ"])
        return out.loss, out.logs

    def evaluate(self, model: nn.Module, loader: Any) -> dict[str, torch.Tensor]:
        device = next(model.parameters()).device
        raw = model.module if hasattr(model, "module") else model
        full = torch.zeros(18, 18, dtype=torch.float64, device=device)
        cam = torch.zeros_like(full)
        for batch in loader:
            occ = batch["occ"].to(device)
            pred = raw.decode(raw.encode(occ))
            full += confusion_stats(pred, occ).to(device)
            cam += confusion_stats(pred, occ, batch["mask_camera"].to(device)).to(device)
        return {"confusion": full, "confusion_camera": cam}

    def compute_metrics(self, stats: dict[str, torch.Tensor]) -> dict[str, float]:
        out = occupancy_metrics(stats["confusion"], "")
        cam = occupancy_metrics(stats["confusion_camera"], "cam/")
        return {**out, "cam/miou": cam["cam/miou"], "cam/iou": cam["cam/iou"]}
