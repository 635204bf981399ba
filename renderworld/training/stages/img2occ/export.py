"""Pseudo labels from a trained Img2Occ: what ``tools/export_occ.py`` runs.

``export_pseudo_labels`` rebuilds the model from an ``img2occ`` checkpoint (its stored config
and readout threshold), runs it over every keyframe of the requested converter splits and writes
Occ3D-layout ``<out>/gts/<scene>/<sample_token>/labels.npz`` (``semantics`` on the model's grid,
``mask_lidar`` / ``mask_camera`` from the dataset's Occ3D ground truth when present, else the
voxels seen by a camera). ``OccSequenceDataset(..., occ_root=out)`` reads them (the tokenizer
and world model "Camera" setting: ``stage.occ_root=<out>``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from renderworld.constants import FREE_ID, OCC3D_CLASSES
from renderworld.training.stages.img2occ.builders import load_img2occ

__all__ = ["ExportSummary", "export_pseudo_labels", "default_export_dir"]


@dataclass
class ExportSummary:
    """What an export wrote.

    Attributes:
        out_dir: the output root (``gts/`` inside it).
        files_per_split: {split: labels.npz files written}.
        step: training step of the checkpoint.
        threshold: the single readout opacity threshold.
        class_thresholds: {class name: threshold} when the checkpoint holds per-class
            thresholds (they are the ones used), else None.
        class_offsets: {class name: logit offset} of the readout's argmax when the
            checkpoint holds calibrated offsets (any non-zero), else None.
        grid: grid name and shape of the labels.
        class_fractions: {class name: fraction of all written voxels}, free included.
    """

    out_dir: Path
    files_per_split: dict[str, int]
    step: int
    threshold: float
    grid: str
    class_fractions: dict[str, float] = field(default_factory=dict)
    class_thresholds: dict[str, float] | None = None
    class_offsets: dict[str, float] | None = None

    def __str__(self) -> str:
        total = sum(self.files_per_split.values())
        occupied = 1.0 - self.class_fractions.get(OCC3D_CLASSES[FREE_ID], 1.0)
        top = sorted(
            ((v, k) for k, v in self.class_fractions.items() if k != OCC3D_CLASSES[FREE_ID]),
            reverse=True,
        )[:5]
        return (
            f"exported {total} samples {self.files_per_split} to {self.out_dir / 'gts'} "
            f"(grid {self.grid}, checkpoint step {self.step}, readout opacity > "
            + ("the per-class thresholds" if self.class_thresholds else f"{self.threshold:g}")
            + (", class = argmax of logits + per-class offsets" if self.class_offsets else "")
            + f"); occupied voxels {100 * occupied:.2f} %, most frequent: "
            + ", ".join(f"{k} {100 * v:.2f} %" for v, k in top)
        )


def default_export_dir(ckpt: str | os.PathLike) -> Path:
    """``<run>/occ_export`` for ``<run>/checkpoints/<x>.pt``, else ``<dir>/<stem>_occ_export``."""
    ckpt = Path(ckpt).resolve()
    if ckpt.parent.name == "checkpoints":
        return ckpt.parent.parent / "occ_export"
    return ckpt.parent / f"{ckpt.stem}_occ_export"


def _splits(folder: Path, split: str) -> list[str]:
    found = sorted(p.stem[len("infos_") :] for p in folder.glob("infos_*.parquet"))
    if not found:
        raise ValueError(f"infos_dir: {folder} holds no infos_<split>.parquet (run create_data)")
    if split == "all":
        return found
    if split not in found:
        raise ValueError(f"split: {split!r} not converted in {folder}; expected all or {found}")
    return [split]


def export_pseudo_labels(
    ckpt: str | os.PathLike,
    data_root: str | os.PathLike,
    version: str = "v1.0-mini",
    out: str | os.PathLike | None = None,
    split: str = "all",
    infos_dir: str | os.PathLike | None = None,
    batch_size: int = 1,
    num_workers: int = 0,
    device: str = "auto",
    progress: bool = True,
) -> ExportSummary:
    """Export a checkpoint's occupancy for every keyframe of the chosen splits.

    Args:
        ckpt: an ``img2occ`` checkpoint (``last.pt`` / ``best.pt``).
        data_root: the dataset folder (images, ``gts/``).
        version: dataset version, locating the default infos folder.
        out: output root; default :func:`default_export_dir`.
        split: ``"all"`` (every converted split) or one split name.
        infos_dir: folder of ``infos_<split>.parquet``; default
            ``<data_root>/renderworld_infos/<version>``.
        batch_size, num_workers: data loading.
        device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda"``...
        progress: tqdm progress bars.

    Returns:
        :class:`ExportSummary` (also written to ``<out>/export_info.json``).

    Raises:
        CheckpointError: not an img2occ checkpoint, or weights that do not fit its config.
        ValueError: missing infos folder or split.
    """
    from renderworld.data import Img2OccDataset, load_infos, load_occ3d_labels
    from renderworld.img2occ import export_occupancy

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    model, meta = load_img2occ(ckpt, device)
    run = OmegaConf.create(meta["config"])
    folder = Path(infos_dir) if infos_dir else Path(data_root) / "renderworld_infos" / version
    if not folder.is_dir():
        raise ValueError(
            f"infos_dir: {folder} does not exist; run tools/create_data.py "
            f"data_root={data_root} version={version} first"
        )
    out_dir = Path(out) if out else default_export_dir(ckpt)
    grid = model.cfg.grid
    counts: dict[str, int] = {}
    hist = np.zeros(len(OCC3D_CLASSES), dtype=np.int64)
    for name in _splits(folder, split):
        data = Img2OccDataset(
            load_infos(folder, name),
            data_root,
            input_size=tuple(run.stage.input_size),
            render_size=tuple(run.stage.render_size),
            grid=grid,
        )
        paths = export_occupancy(
            model, data, out_dir, batch_size, num_workers, device=device, progress=progress
        )
        counts[name] = len(paths)
        for p in paths:
            sem = load_occ3d_labels(p, expected_shape=grid.shape).semantics
            hist += np.bincount(sem.reshape(-1), minlength=len(OCC3D_CLASSES))
    summary = _summary(model, meta, out_dir, counts, hist)
    _write_info(summary, ckpt, data_root, folder, grid)
    return summary


def _summary(model, meta: dict, out_dir: Path, counts: dict, hist: np.ndarray) -> ExportSummary:
    """What an export wrote: files per split, the readout it used, class fractions."""
    grid = model.cfg.grid
    fractions = {c: float(n) / max(int(hist.sum()), 1) for c, n in zip(OCC3D_CLASSES, hist)}
    return ExportSummary(
        out_dir=out_dir,
        files_per_split=counts,
        step=int(meta["step"]),
        threshold=float(model.occupancy_threshold),
        grid=f"{grid.name} {list(grid.shape)}",
        class_fractions=fractions,
        class_thresholds=(
            dict(zip(OCC3D_CLASSES, model.class_thresholds.tolist()))
            if bool((model.class_thresholds >= 0).all())
            else None
        ),
        class_offsets=(
            dict(zip(OCC3D_CLASSES, model.class_offsets.tolist()))
            if bool((model.class_offsets != 0).any())
            else None
        ),
    )


def _write_info(summary: ExportSummary, ckpt, data_root, folder: Path, grid) -> None:
    """``<out>/export_info.json``: the summary plus where the labels came from."""
    info = {
        "checkpoint": str(Path(ckpt).resolve()),
        "data_root": str(Path(data_root).resolve()),
        "infos_dir": str(folder.resolve()),
        "step": summary.step,
        "threshold": summary.threshold,
        "class_thresholds": summary.class_thresholds,
        "class_offsets": summary.class_offsets,
        "grid": {"name": grid.name, "shape": list(grid.shape)},
        "files_per_split": summary.files_per_split,
        "class_fractions": summary.class_fractions,
    }
    summary.out_dir.mkdir(parents=True, exist_ok=True)
    (summary.out_dir / "export_info.json").write_text(json.dumps(info, indent=2) + "\n")
