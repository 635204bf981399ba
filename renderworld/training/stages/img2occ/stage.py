"""The ``img2occ`` stage: camera images → semantic Gaussians → 3-D occupancy (paper §6.2.1).

Training: ``Img2OccDataset`` keyframes of the converter's train split (plus, with
``stage.adjacent_frames = k``, the k previous / next keyframes' cameras as label-only views);
loss = the model's rendered-semantics NLL + Pearson depth (+ the optional relative-depth L1, + the
depth-aware lifting's per-pixel depth-bin / class CE against the 2-D labels with
``stage.model.depth_bins > 0``); ``stage.model.supervision = 3d`` trains the same network on
Occ3D GT voxels instead (the upper reference, ``experiment=img2occ_mini_3dgt``).

Evaluation, Occ3D protocol (docs/protocol.md#occupancy): the readout (opacity > the model's stored
threshold, class = argmax) is compared with the Occ3D ground truth on the run's grid; 18x18
confusions are summed over the split (and over ranks) inside the camera mask (``cam/``, Occ3D
official, with per-class IoU), inside the LiDAR mask (``lidar/``) and on the full volume
(``full/``). mIoU = nanmean over classes 0..16, free excluded; ``iou`` = geometry IoU (occupied vs
free).

Readout threshold: at the end of training (rank 0) ``choose_threshold`` picks it on the TRAINING
split (criterion ``stage.threshold.criterion``, camera mask) for the weights of ``last.pt`` and,
separately, of ``best.pt``; each checkpoint is re-written atomically with its threshold in the
model state (buffer ``occupancy_threshold``), a ``threshold`` record and its validation metrics
recomputed with that threshold. Validation during training uses the threshold the model holds
(``stage.model.occupancy_threshold`` for a fresh run), so ``best.pt`` is picked at that one.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset, default_collate

from renderworld.constants import OCC3D_CLASSES
from renderworld.data.cache import CachedDataset
from renderworld.img2occ import Img2Occ, draw_views
from renderworld.precision import autocast_off, exact_float32
from renderworld.training.registry import Stage, register_stage
from renderworld.training.stages.common import (
    confusion_stats,
    evaluated_checkpoint,
    occupancy_metrics,
)
from renderworld.training.stages.img2occ.builders import (
    _adjacent,
    checkpoint_architecture,
    img2occ_config,
    img2occ_datasets,
)
from renderworld.training.stages.img2occ.threshold import (
    ThresholdMixin,
    _offset_options,
    _refit_root,
    _threshold_options,
)

__all__ = ["Img2OccStage", "occ3d_report_markdown", "MASKS"]

log = logging.getLogger("renderworld.training")

#: Metric prefixes and the region each covers (every confusion is summed over the split).
MASKS = {
    "cam/": "camera mask (Occ3D official)",
    "lidar/": "LiDAR mask",
    "full/": "full volume",
}


def _fmt(value: float | None) -> str:
    return "–" if value is None or value != value else f"{100 * value:.2f}"


def occ3d_report_markdown(metrics: dict[str, float], title: str, notes: list[str]) -> str:
    """A markdown report of Occ3D-protocol metrics (``val/<mask>/...`` keys, fractions).

    Per-class IoU inside the camera mask (classes 0..16, "–" = absent from GT and prediction,
    left out of the mean), then mIoU and geometry IoU for each mask. Values in percent.
    """
    from renderworld.metrics.occupancy import OCCUPANCY_PROTOCOL

    lines = [f"# {title}", "", *[f"- {n}" for n in notes], f"- protocol: {OCCUPANCY_PROTOCOL}"]
    lines += ["", "## Per-class IoU, camera mask (Occ3D official), %", ""]
    lines += ["| id | class | IoU |", "|---:|---|---:|"]
    for c, name in enumerate(OCC3D_CLASSES[:-1]):
        lines.append(f"| {c} | {name} | {_fmt(metrics.get(f'val/cam/iou_{name}'))} |")
    lines += [
        "",
        "## Summary, %",
        "",
        "| region | mIoU (0..16) | geometry IoU |",
        "|---|---:|---:|",
    ]
    for prefix, label in MASKS.items():
        miou, iou = metrics.get(f"val/{prefix}miou"), metrics.get(f"val/{prefix}iou")
        lines.append(f"| {label} | {_fmt(miou)} | {_fmt(iou)} |")
    return "\n".join(lines) + "\n"


@register_stage("img2occ")
class Img2OccStage(ThresholdMixin, Stage):
    """Img2Occ training and Occ3D-protocol evaluation (see the module docstring)."""

    def __init__(self, cfg: Any) -> None:
        super().__init__(cfg)
        self._val: Dataset | None = None

    # ------------------------------------------------------------------ build
    def build_model(self, cfg: Any) -> nn.Module:
        """The Img2Occ; when evaluating (``ckpt`` set) its architecture is the checkpoint's
        (:func:`checkpoint_architecture`), so a run trained with another ``stage.model`` (e.g.
        ``depth_bins=20``) evaluates as itself."""
        mine = img2occ_config(cfg)
        ckpt = evaluated_checkpoint(cfg)
        if ckpt is None:
            return Img2Occ(mine)
        return Img2Occ(checkpoint_architecture(mine, ckpt))

    def build_datasets(self, cfg: Any) -> tuple[Dataset, Dataset | None]:
        img2occ_config(cfg)  # fail on a bad model or threshold config before any data is read
        _threshold_options(cfg)
        _offset_options(cfg)
        _refit_root(cfg)
        train = img2occ_datasets(cfg, cfg.dataset.train_split, _adjacent(cfg))
        # Evaluation reads the readout only: no adjacent views to load.
        self._val = img2occ_datasets(cfg, cfg.dataset.val_split)
        if cfg.stage.get("cache_samples", False):
            if int(cfg.trainer.get("num_workers", 0)) > 0:
                warnings.warn(
                    "stage.cache_samples: ignored with trainer.num_workers > 0 (each worker "
                    "process would fill its own copy); set num_workers=0 to cache",
                    RuntimeWarning,
                    stacklevel=2,
                )
            else:
                train, self._val = CachedDataset(train), CachedDataset(self._val)
        return train, self._val

    # ------------------------------------------------------------------ train
    def loss(self, model: nn.Module, batch: Any) -> tuple[torch.Tensor, dict[str, Any]]:
        raw = model.module if hasattr(model, "module") else model
        batch = raw.augment(batch)
        return raw.loss(batch, model(batch))

    # ------------------------------------------------------------------ evaluate
    def evaluate(self, model: nn.Module, loader: Any) -> dict[str, torch.Tensor]:
        raw = model.module if hasattr(model, "module") else model
        device = next(raw.parameters()).device
        # Summed on the model's device: no host sync per validation batch.
        stats = {
            "confusion_cam": torch.zeros(18, 18, dtype=torch.float64, device=device),
            "confusion_lidar": torch.zeros(18, 18, dtype=torch.float64, device=device),
            "confusion_full": torch.zeros(18, 18, dtype=torch.float64, device=device),
            "samples": torch.zeros((), dtype=torch.float64, device=device),
        }
        # The readout decides labels: float32 without TF32 under any training precision, so a
        # checkpoint scores the same on CPU and CUDA (renderworld.precision.exact_float32).
        with exact_float32(), autocast_off():
            for batch in loader:
                self._evaluate_batch(raw, batch, device, stats)
        return stats

    def _evaluate_batch(self, raw: nn.Module, batch: Any, device, stats: dict) -> None:
        missing = [k for k in ("occ", "mask_camera", "mask_lidar") if k not in batch]
        if missing:
            tokens = batch.get("meta", {}).get("sample_token", "?")
            raise ValueError(
                f"validation batch (samples {tokens}) lacks {missing}: the Occ3D protocol "
                "needs Occ3D ground truth (gts/<scene>/<token>/labels.npz) for every "
                "validation sample"
            )
        batch = self.transfer_batch(batch, device)
        pred = raw.readout(raw(batch, render=False))
        occ = batch["occ"]
        stats["confusion_cam"] += confusion_stats(pred, occ, batch["mask_camera"])
        stats["confusion_lidar"] += confusion_stats(pred, occ, batch["mask_lidar"])
        stats["confusion_full"] += confusion_stats(pred, occ)
        stats["samples"] += occ.shape[0]

    def compute_metrics(self, stats: dict[str, torch.Tensor]) -> dict[str, float]:
        out = occupancy_metrics(stats["confusion_cam"], "cam/")
        for prefix, key in (("lidar/", "confusion_lidar"), ("full/", "confusion_full")):
            m = occupancy_metrics(stats[key], prefix)
            out[f"{prefix}miou"], out[f"{prefix}iou"] = m[f"{prefix}miou"], m[f"{prefix}iou"]
        out["samples"] = float(stats["samples"])
        return out

    # ------------------------------------------------------------------ threshold
    def _loader(self, dataset: Dataset) -> DataLoader:
        tr = self.cfg.trainer
        return DataLoader(
            dataset,
            batch_size=int(tr.get("val_batch_size") or tr.batch_size),
            shuffle=False,
            num_workers=int(tr.get("num_workers", 0)),
        )

    def _val_metrics(self, model: nn.Module) -> dict[str, float]:
        if self._val is None:
            return {}
        model.eval()
        with torch.no_grad():
            stats = self.evaluate(model, self._loader(self._val))
        return {f"val/{k}": float(v) for k, v in self.compute_metrics(stats).items()}

    # ------------------------------------------------------------------ report
    def on_eval_end(self, model: nn.Module, metrics: dict[str, float], run_dir: str) -> None:
        """Write ``img2occ_views.png`` and ``occ3d_metrics.md`` into the eval run dir."""
        out = Path(run_dir)
        raw = model.module if hasattr(model, "module") else model
        threshold = float(raw.occupancy_threshold)
        per_class = raw.class_thresholds.tolist()
        refit = getattr(self, "refit_record", None)
        stored = "stored"
        rule = f"opacity > {threshold:g} (the checkpoint's stored threshold)"
        if refit:  # stage.threshold.refit_root: re-chosen for these weights before scoring
            stored = f"re-chosen (on `{refit['root']}`)"
            rule = f"opacity > {threshold:g} (re-chosen on `{refit['root']}`)"
            (out / "threshold_refit.json").write_text(json.dumps(refit, indent=2) + "\n")
        if min(per_class) >= 0:
            rule = (
                f"opacity > the {stored} per-class threshold of the argmax class ("
                + ", ".join(f"{c} {t:g}" for c, t in zip(OCC3D_CLASSES, per_class))
                + ")"
            )
        offsets = raw.class_offsets.tolist()
        argmax = "argmax of the Gaussian's logits"
        if any(offsets):
            argmax = (
                f"argmax of the Gaussian's logits plus the {stored} per-class offsets ("
                + ", ".join(f"{c} {o:+g}" for c, o in zip(OCC3D_CLASSES, offsets) if o)
                + ")"
            )
        notes = [
            f"checkpoint: `{self.cfg.get('ckpt')}` (step {int(metrics.get('step', -1))})",
            f"split: `{self.cfg.dataset.val_split}`, {int(metrics.get('val/samples', 0))} "
            f"samples, grid `{self.cfg.grid.name}` {list(self.cfg.grid.shape)}",
            f"readout: {rule}, class = {argmax}",
        ]
        text = occ3d_report_markdown(metrics, "Img2Occ occupancy, Occ3D protocol", notes)
        (out / "occ3d_metrics.md").write_text(text)
        if self._val is None or len(self._val) == 0:
            return
        index = int(self.cfg.stage.get("report_sample", 0))
        if not 0 <= index < len(self._val):
            raise ValueError(f"stage.report_sample: expected 0..{len(self._val) - 1}, got {index}")
        device = next(raw.parameters()).device
        batch = self.transfer_batch(default_collate([self._val[index]]), device)
        was_training = raw.training
        raw.eval()
        try:
            with torch.no_grad():
                output = raw(batch, render=True)
        finally:
            raw.train(was_training)
        draw_views(batch, output, out / "img2occ_views.png")
