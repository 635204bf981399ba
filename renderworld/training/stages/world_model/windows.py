"""Training and validation windows of the ``world_model`` stage.

:class:`WorldModelWindows` are ``OccSequenceDataset`` windows of ``history + future`` keyframes
(each future frame's pose included, for the collision-vs-occupancy metric), with the dataset's GT
targets beside pseudo-label inputs in the Camera setting; :func:`frame_keys` gives the key of
each frame of a collated batch (the stage's token cache keys codes by it).

A frame's key is its data root and its sample token: two datasets whose sample tokens collide
(the training fixture and a scenario library, two fixtures simulated with the same scene names)
never share codes. Each item carries its own root (``meta.data_root``), so the key follows the
item through a ``ConcatDataset`` of several roots (``stage.extra_train_roots``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from torch.utils.data import Dataset

from renderworld.data import OccSequenceDataset

__all__ = ["WorldModelWindows", "frame_keys"]


class WorldModelWindows(Dataset):
    """``OccSequenceDataset`` windows (with GT targets in the Camera setting).

    ``frame_cache``: folder of the on-disk frame cache (see ``OccSequenceDataset``) or None.

    With ``occ_root`` (pseudo labels) and ``gt_targets``, items also carry the dataset's GT
    ``occ_target`` uint8 [T,X,Y,Z] and ``mask_camera_target`` bool [T,X,Y,Z] of the same window,
    which evaluation scores against (the "Camera" setting).

    The items' ``future_poses[k]`` (from ``OccSequenceDataset``) = (x, y, yaw) of future frame
    k's ego frame in the current (last history) ego frame, metres / radians: where each future
    GT occupancy frame lies, for the collision-vs-occupancy metric. Their ``meta.data_root`` is
    :attr:`data_root` (see :func:`frame_keys`).

    Attributes:
        data_root: the resolved path of the data root the windows are read from (str).
    """

    def __init__(
        self,
        infos,
        data_root,
        grid,
        history,
        future,
        occ_root=None,
        gt_targets=False,
        frame_cache=None,
    ):
        self.data_root = str(Path(data_root).resolve())
        self.seq = OccSequenceDataset(
            infos, data_root, history=history, future=future, grid=grid, occ_root=occ_root,
            frame_cache=frame_cache,
        )  # fmt: skip
        # Camera setting: inputs are pseudo labels (occ_root) but forecasts are scored against
        # the dataset's GT; the GT windows are the same windows (same infos, history, future).
        self.gt = None
        if occ_root is not None and gt_targets:
            self.gt = OccSequenceDataset(
                infos, data_root, history=history, future=future, grid=grid, occ_root=None,
                frame_cache=frame_cache,
            )  # fmt: skip

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int) -> dict[str, Any]:
        item = self.seq[i]
        if self.gt is not None:
            gt = self.gt[i]
            item["occ_target"], item["mask_camera_target"] = gt["occ"], gt["mask_camera"]
        item["meta"]["data_root"] = self.data_root
        return item


def frame_keys(batch: dict, b: int, t: int) -> list[list[str]]:
    """Keys [B][T] of the frames of a collated batch: ``"<data root>/<sample token>"``.

    Args:
        batch: default-collated :class:`WorldModelWindows` items: ``meta.sample_tokens`` is T
            lists of B tokens, ``meta.data_root`` B resolved root paths (one per window).
        b: B, windows in the batch.
        t: T, frames per window.

    Raises:
        ValueError: naming ``batch`` when ``meta`` lacks either or they do not match B and T.
    """
    meta = batch["meta"]
    toks, roots = meta["sample_tokens"], meta.get("data_root")
    if len(toks) != t or any(len(col) != b for col in toks):
        raise ValueError(
            f"batch: expected meta.sample_tokens as {t} lists of {b} tokens (default collate)"
        )
    if roots is None or isinstance(roots, str) or len(roots) != b:
        raise ValueError(
            f"batch: expected meta.data_root as {b} data roots, one per window (WorldModelWindows "
            f"items carry it), got {roots!r}"
        )
    return [[f"{roots[i]}/{toks[j][i]}" for j in range(t)] for i in range(b)]
