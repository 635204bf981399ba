"""Export the model's occupancy as Occ3D-layout pseudo labels (``gts/<scene>/<token>/labels.npz``).

The semantics are ``Img2Occ.readout`` (threshold from the model's state). Masks come from the
dataset item (``mask_lidar``, ``mask_camera``) when it has Occ3D GT; for samples without GT
both masks are the voxels seen by at least one camera (the lifting's visibility), so
downstream camera-mask metrics still have a defined observed region.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import torch

from renderworld.precision import autocast_off, exact_float32

__all__ = ["export_occupancy", "batch_to_device"]

# Scene names and sample tokens become path components: keep them plain.
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


def batch_to_device(batch, device):
    """Move every tensor of a (nested) batch to ``device``; other values are kept."""
    if isinstance(batch, torch.Tensor):
        return batch.to(device)
    if isinstance(batch, dict):
        return {k: batch_to_device(v, device) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        return type(batch)(batch_to_device(v, device) for v in batch)
    return batch


def _name(kind: str, value) -> str:
    value = str(value)
    if not _SAFE_NAME.match(value) or ".." in value:
        raise ValueError(
            f"meta.{kind}: {value!r} is not a safe path component (letters, digits, '._-')"
        )
    return value


@torch.no_grad()
def export_occupancy(
    model,
    dataset,
    out_dir: str | os.PathLike,
    batch_size: int = 1,
    num_workers: int = 0,
    device: str | torch.device | None = None,
    progress: bool = True,
) -> list[Path]:
    """Write ``<out_dir>/gts/<scene>/<sample_token>/labels.npz`` for every dataset item.

    Args:
        model: a trained :class:`~renderworld.img2occ.Img2Occ` (its stored threshold is used).
        dataset: a map-style dataset of Img2OccDataset items (``meta`` with ``scene`` and
            ``sample_token``; ``mask_lidar`` / ``mask_camera`` used when present).
        out_dir: output root.
        batch_size: items per forward pass.
        num_workers: DataLoader workers.
        device: where to run; default the model's parameters' device.
        progress: show a tqdm progress bar.

    Returns:
        Written paths, in dataset order.

    Raises:
        ValueError: bad batch_size, a mask of the wrong shape, or an unsafe scene/token name.
    """
    from torch.utils.data import DataLoader

    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size <= 0:
        raise ValueError(f"batch_size: expected a positive int, got {batch_size!r}")
    if device is None:
        device = next(model.parameters()).device
    out_root = Path(out_dir)
    grid_shape = tuple(model.cfg.grid.shape)
    loader = DataLoader(dataset, batch_size=batch_size, shuffle=False, num_workers=num_workers)
    was_training = model.training
    model.eval()
    # Labels decided in float32 without TF32 (renderworld.precision.exact_float32): the same
    # checkpoint exports the same labels on CPU and CUDA, up to float32 summation order.
    with exact_float32(), autocast_off():
        return _export(model, loader, out_root, grid_shape, device, progress, was_training)


def _export(model, loader, out_root: Path, grid_shape, device, progress, was_training):
    from tqdm import tqdm

    from renderworld.data import save_occ3d_labels

    written: list[Path] = []
    try:
        bar = tqdm(loader, desc="export occupancy", unit="batch", disable=not progress)
        for batch in bar:
            batch = batch_to_device(batch, device)
            out = model(batch, render=False)
            sem = model.readout(out).cpu().numpy()
            seen = (out.visibility > 0).cpu().numpy()
            meta = batch.get("meta", {})
            if "scene" not in meta or "sample_token" not in meta:
                raise ValueError("dataset: items need meta.scene and meta.sample_token to export")
            for i in range(sem.shape[0]):
                masks = []
                for key in ("mask_lidar", "mask_camera"):
                    m = batch[key][i].cpu().numpy() if key in batch else seen[i]
                    if tuple(m.shape) != grid_shape:
                        raise ValueError(
                            f"{key}: expected the model grid {grid_shape}, got {tuple(m.shape)}"
                        )
                    masks.append(m)
                scene = _name("scene", meta["scene"][i])
                token = _name("sample_token", meta["sample_token"][i])
                path = out_root / "gts" / scene / token / "labels.npz"
                written.append(save_occ3d_labels(path, sem[i], masks[0], masks[1]))
    finally:
        model.train(was_training)
    return written
