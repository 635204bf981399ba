"""Training and validation windows of the ``world_model`` stage.

:class:`WorldModelWindows` are ``OccSequenceDataset`` windows of ``history + future`` keyframes
(each future frame's pose included, for the collision-vs-occupancy metric), with the dataset's GT
targets beside pseudo-label inputs in the Camera setting; :func:`frame_keys` reads the sample
tokens of a collated batch (the keys of the stage's token cache).
"""

from __future__ import annotations

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
    GT occupancy frame lies, for the collision-vs-occupancy metric.
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
        return item


def frame_keys(batch: dict, b: int, t: int) -> list[list[str]]:
    """Sample tokens [B][T] of a collated batch (``meta.sample_tokens`` is T lists of B)."""
    toks = batch["meta"]["sample_tokens"]
    if len(toks) != t or any(len(col) != b for col in toks):
        raise ValueError(
            f"batch: expected meta.sample_tokens as {t} lists of {b} tokens (default collate)"
        )
    return [[str(toks[j][i]) for j in range(t)] for i in range(b)]
