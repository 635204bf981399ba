"""Readout-threshold selection of the ``img2occ`` stage (a mixin of ``Img2OccStage``).

At the end of training (rank 0) ``choose_threshold`` picks the readout threshold on the
TRAINING split (criterion ``stage.threshold.criterion``, camera mask; with
``stage.threshold.per_class`` also one per class, with ``class_offsets`` also per-class logit
offsets of the argmax) for the weights of ``last.pt`` and,
separately, of ``best.pt``; each checkpoint is re-written atomically with its thresholds in the
model state, a ``threshold`` record and its validation metrics recomputed with them.

When evaluating, ``stage.threshold.refit_root`` re-chooses it the same way for the evaluated
weights on another data root's training split (e.g. to compare readout options on a
development split without retraining); the checkpoint file is left as it is.
"""

from __future__ import annotations

import copy
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import open_dict
from torch import nn
from torch.utils.data import Dataset, Subset

from renderworld.constants import OCC3D_CLASSES
from renderworld.img2occ import Img2Occ, choose_threshold
from renderworld.img2occ.calibration import DEFAULT_OFFSETS
from renderworld.img2occ.readout import DEFAULT_THRESHOLDS
from renderworld.precision import autocast_off, exact_float32
from renderworld.training.checkpoint import load_checkpoint, save_checkpoint
from renderworld.training.stages.img2occ.builders import img2occ_datasets

__all__ = ["ThresholdMixin"]

log = logging.getLogger("renderworld.training")


def _threshold_options(cfg: Any) -> tuple[str, list[float], int | None, bool]:
    """(criterion, candidates, max_samples, per_class) of ``stage.threshold``, validated."""
    t = cfg.stage.get("threshold") or {}
    criterion = str(t.get("criterion", "miou"))
    if criterion not in ("miou", "iou"):
        raise ValueError(f"stage.threshold.criterion: expected 'miou' or 'iou', got {criterion!r}")
    raw = t.get("candidates")
    candidates = list(DEFAULT_THRESHOLDS) if raw is None else [float(v) for v in raw]
    if not candidates or not all(0.0 <= v < 1.0 for v in candidates):
        raise ValueError(f"stage.threshold.candidates: expected values in [0, 1), got {raw!r}")
    cap = t.get("max_samples")
    if cap is not None and (isinstance(cap, bool) or not isinstance(cap, int) or cap < 1):
        raise ValueError(f"stage.threshold.max_samples: expected null or an int >= 1, got {cap!r}")
    per_class = t.get("per_class", False)
    if not isinstance(per_class, bool) or (per_class and criterion != "miou"):
        raise ValueError(
            f"stage.threshold.per_class: expected true (with criterion miou) or false, got "
            f"{per_class!r} with criterion {criterion!r}"
        )
    return criterion, candidates, cap, per_class


def _offset_options(cfg: Any) -> tuple[bool, list[float], int]:
    """(class_offsets, offset_candidates, offset_rounds) of ``stage.threshold``, validated."""
    t = cfg.stage.get("threshold") or {}
    on = t.get("class_offsets", False)
    per_class = _threshold_options(cfg)[3]
    if not isinstance(on, bool) or (on and not per_class):
        raise ValueError(
            f"stage.threshold.class_offsets: expected true (with per_class true) or false, got "
            f"{on!r} with per_class {per_class!r}"
        )
    raw = t.get("offset_candidates")
    cands = list(DEFAULT_OFFSETS) if raw is None else [float(v) for v in raw]
    if 0.0 not in cands or not all(np.isfinite(cands)):
        raise ValueError(
            f"stage.threshold.offset_candidates: expected finite values including 0, got {raw!r}"
        )
    rounds = t.get("offset_rounds", 2)
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"stage.threshold.offset_rounds: expected an int >= 1, got {rounds!r}")
    return on, cands, rounds


def _refit_root(cfg: Any) -> Path | None:
    """``stage.threshold.refit_root``: None, or the existing data root whose training split
    re-chooses the readout when evaluating."""
    raw = (cfg.stage.get("threshold") or {}).get("refit_root")
    if raw is None:
        return None
    path = Path(str(raw))
    if not path.is_dir():
        raise ValueError(
            f"stage.threshold.refit_root: {str(raw)!r} is not a folder (expected a data root "
            f"converted by tools/create_data.py, or null for the checkpoint's stored readout)"
        )
    return path


def _is_main() -> bool:
    dist = torch.distributed
    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0


class ThresholdMixin:
    """``on_train_end`` threshold selection; needs the Stage's ``cfg``, ``name``, ``_loader``,
    ``transfer_batch`` and ``_val_metrics``."""

    def _threshold_set(self, cfg: Any = None) -> Dataset:
        cfg = self.cfg if cfg is None else cfg
        data = img2occ_datasets(cfg, cfg.dataset.train_split)
        cap = _threshold_options(cfg)[2]
        if cap is not None and cap < len(data):
            # Evenly spaced over the split (every scene contributes), deterministic.
            idx = np.unique(np.linspace(0, len(data) - 1, cap).round().astype(int))
            data = Subset(data, idx.tolist())
        return data

    def _choose(self, model: Img2Occ, data: Dataset) -> dict[str, Any]:
        criterion, candidates, _, per_class = _threshold_options(self.cfg)
        offsets, offset_candidates, rounds = _offset_options(self.cfg)
        device = next(model.parameters()).device
        batches = (self.transfer_batch(b, device) for b in self._loader(data))
        initial = float(model.occupancy_threshold)
        # Labels decided in float32 without TF32: the same choice on CPU and CUDA.
        with exact_float32(), autocast_off():
            value, scores = choose_threshold(
                model, batches, candidates, criterion, True, per_class, offsets,
                offset_candidates, rounds,
            )  # fmt: skip
        return {
            "value": value,
            "per_class": (
                {c: round(t, 6) for c, t in zip(OCC3D_CLASSES, model.class_thresholds.tolist())}
                if per_class
                else None
            ),
            "class_offsets": (
                {c: round(o, 6) for c, o in zip(OCC3D_CLASSES, model.class_offsets.tolist())}
                if offsets
                else None
            ),
            "initial": initial,
            "criterion": criterion,
            "mask": "camera",
            "split": str(self.cfg.dataset.train_split),
            "samples": len(data),
            "scores": {f"{t:g}": s for t, s in scores.items()},
        }

    def on_eval_start(self, model: nn.Module) -> None:
        """``stage.threshold.refit_root`` set: re-choose the readout of the evaluated weights
        under the run's ``stage.threshold`` options, on that root's training split (its
        converter infos; ``stage.infos_dir`` only when it is the evaluated root), exactly as at
        the end of training, before scoring. The checkpoint file is not changed; the record is
        kept for ``threshold_refit.json`` in the eval run dir."""
        self.refit_record: dict[str, Any] | None = None
        root = _refit_root(self.cfg)
        if root is None:
            return
        cfg = copy.deepcopy(self.cfg)
        with open_dict(cfg):
            if root.resolve() != Path(str(cfg.dataset.data_root)).resolve():
                cfg.stage.infos_dir = None
            cfg.dataset.data_root = str(root)
        raw = model.module if hasattr(model, "module") else model
        # From a fresh model's readout, as at the end of training: the checkpoint's per-class
        # thresholds and offsets would otherwise still apply where the options turn them off.
        raw.class_thresholds.fill_(-1.0)
        raw.class_offsets.zero_()
        was_training = raw.training
        try:
            record = self._choose(raw, self._threshold_set(cfg))
        finally:
            raw.train(was_training)
        self.refit_record = {"root": str(root), **record}
        log.info(
            "readout re-chosen on %s (%s split, %d samples): threshold %g%s%s",
            root,
            record["split"],
            record["samples"],
            record["value"],
            ", per class" if record["per_class"] else "",
            ", with class offsets" if record["class_offsets"] else "",
        )

    def on_train_end(self, model: nn.Module, run_dir: str) -> dict[str, float] | None:
        """Rank 0: choose the readout threshold for ``last.pt`` and ``best.pt`` and re-save them.

        Each checkpoint gets the threshold chosen on the training split for its own weights,
        stored in ``model["occupancy_threshold"]``, a ``threshold`` record (value, criterion,
        scores per candidate, the validation metrics at the initial threshold) and ``metrics``
        recomputed on the validation split with it; ``<run_dir>/threshold.json`` sums it up.
        The in-memory model ends with ``last.pt``'s threshold.

        Returns:
            ``last.pt``'s validation metrics with its readout (None on other ranks).
        """
        if not _is_main():
            return None
        ckpt_dir = Path(run_dir) / "checkpoints"
        data = self._threshold_set()
        was_training = model.training
        summary: dict[str, Any] = {}
        try:
            last = load_checkpoint(ckpt_dir / "last.pt", expected_stage=self.name)
            record = self._choose(model, data)
            last_metrics = self._val_metrics(model)
            self._resave(ckpt_dir / "last.pt", last, model, record, last_metrics)
            summary["last.pt"] = {"step": last["step"], **record, "val_metrics": last_metrics}
            best_path = ckpt_dir / "best.pt"
            if best_path.is_file():
                best = load_checkpoint(best_path, expected_stage=self.name)
                if int(best["step"]) == int(last["step"]):  # same weights: same threshold
                    best_record, best_metrics, src = record, last_metrics, model
                else:
                    src = copy.deepcopy(model)
                    src.load_state_dict(best["model"], strict=True)
                    best_record = self._choose(src, data)
                    best_metrics = self._val_metrics(src)
                self._resave(best_path, best, src, best_record, best_metrics)
                summary["best.pt"] = {
                    "step": best["step"],
                    **best_record,
                    "val_metrics": best_metrics,
                }
        finally:
            model.train(was_training)
        path = Path(run_dir) / "threshold.json"
        path.write_text(json.dumps(summary, indent=2) + "\n")
        log.info(
            "readout threshold chosen on the %s split (%d samples, %s, camera mask): %s; "
            "val cam/miou with it: %s",
            self.cfg.dataset.train_split,
            len(data),
            summary["last.pt"]["criterion"],
            {k: v["value"] for k, v in summary.items()},
            {k: v["val_metrics"].get("val/cam/miou") for k, v in summary.items()},
        )
        return summary["last.pt"]["val_metrics"]

    @staticmethod
    def _resave(path: Path, ckpt: dict, model: Img2Occ, record: dict, metrics: dict) -> None:
        ckpt = dict(ckpt)
        state = dict(ckpt["model"])
        state["occupancy_threshold"] = model.occupancy_threshold.detach().cpu().clone()
        state["class_thresholds"] = model.class_thresholds.detach().cpu().clone()
        state["class_offsets"] = model.class_offsets.detach().cpu().clone()
        ckpt["model"] = state
        record = dict(record, metrics_at_initial=dict(ckpt.get("metrics") or {}))
        ckpt["threshold"] = record
        if metrics:
            ckpt["metrics"] = metrics
        save_checkpoint(ckpt, path)
