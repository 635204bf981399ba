"""Learned mover motion: each road user's future displacement from its track and its scene.

The constant-velocity rule moves a car that is braking at its old speed, a car that merges
straight on, a pedestrian waiting at the kerb into the road. :class:`MoverHead` reads, for each
mover tracked through the whole history (:func:`renderworld.world.tracks.track_movers`):

* its track: the centroid at each of the H history frames relative to its current one (with a
  mask where it was not seen), its fitted velocity, its class, its footprint's size and where
  it is relative to the ego;
* the ego's own history (its step lengths and heading changes);
* the scene around it: a ``PATCH`` x ``PATCH`` bird's-eye window of the current frame centred
  on its cell, channels road, other ground, static obstacles, other movers and itself;

and predicts its displacement at each of the S future steps as a residual on the track's
constant-velocity extrapolation (the last layer starts at zero: an untrained head is the
constant-velocity rule). Frames: the current ego frame (x forward, y left; metres, seconds).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from renderworld.constants import KEYFRAME_DT, MOVABLE_CLASS_IDS, OCC3D_CLASSES, GridSpec
from renderworld.world.tracks import MoverTrack

__all__ = ["CHANNELS", "PATCH", "MoverHead", "MoverInputs", "mirror_inputs", "mover_inputs"]

#: Side of the bird's-eye window around a mover, cells (odd: centred on its cell).
PATCH = 9
_ROAD = OCC3D_CLASSES.index("driveable_surface")
_GROUND = tuple(OCC3D_CLASSES.index(c) for c in ("other_flat", "sidewalk", "terrain"))
_STATIC = (0, 1, 8, OCC3D_CLASSES.index("manmade"), OCC3D_CLASSES.index("vegetation"))
CHANNELS = 5  # road, other ground, static obstacles, other movers, the mover itself


class MoverInputs:
    """The head's inputs for N movers of one window.

    Attributes:
        feats: [N, F] float32 track, class, footprint and ego features.
        patches: [N, CHANNELS, PATCH, PATCH] float32 bird's-eye windows.
        base: [N, S, 2] float32 constant-velocity displacements (metres).
    """

    def __init__(self, feats: np.ndarray, patches: np.ndarray, base: np.ndarray):
        self.feats, self.patches, self.base = feats, patches, base

    def __len__(self) -> int:
        return len(self.feats)


def feature_size(history: int) -> int:
    """F, the width of :attr:`MoverInputs.feats` for ``history`` frames."""
    return 3 * history + 2 + len(MOVABLE_CLASS_IDS) + 5 + 2 * (history - 1)


def mirror_inputs(inputs: MoverInputs, history: int) -> MoverInputs:
    """The inputs of the scene mirrored about the ego's x axis (y -> -y): as plausible a scene,
    for training on twice the data."""
    f = inputs.feats.copy()
    h = history
    f[:, 1 : 2 * h : 2] *= -1  # relative centroids' y
    f[:, 3 * h + 1] *= -1  # velocity's y
    f[:, 3 * h + 2 + len(MOVABLE_CLASS_IDS) + 4] *= -1  # current centroid's y
    f[:, -(h - 1) :] *= -1  # the ego's heading changes
    base = inputs.base.copy()
    base[..., 1] *= -1
    return MoverInputs(f, np.ascontiguousarray(inputs.patches[..., ::-1]), base)


def _scene_planes(current: np.ndarray, tracks: Sequence[MoverTrack]) -> np.ndarray:
    """[CHANNELS - 1, X, Y] float32 bird's-eye planes of the current frame (self excluded)."""
    road = (current == _ROAD).any(-1)
    ground = np.isin(current, _GROUND).any(-1) & ~road
    static = np.isin(current[..., :2], _STATIC).any(-1)
    movers = np.zeros(current.shape[:2], dtype=bool)
    for tr in tracks:
        movers |= tr.cells
    return np.stack([road, ground, static, movers]).astype(np.float32)


def mover_inputs(
    current: np.ndarray,
    history_poses: np.ndarray,
    tracks: Sequence[MoverTrack],
    grid: GridSpec,
    steps: int,
    dt: float = KEYFRAME_DT,
) -> MoverInputs:
    """The head's inputs (module docstring) for the tracked movers of one window.

    Args:
        current: [X, Y, Z] integer labels of the current frame, on ``grid``.
        history_poses: [H, 3] (x, y, yaw) of the history frames in the current ego frame.
        tracks: the movers (:func:`~renderworld.world.tracks.track_movers` of that history).
        grid: the occupancy grid.
        steps: S future steps.
        dt: seconds between frames.
    """
    hp = np.asarray(history_poses, dtype=np.float64)
    h = len(hp)
    n = len(tracks)
    feats = np.zeros((n, feature_size(h)), dtype=np.float32)
    patches = np.zeros((n, CHANNELS, PATCH, PATCH), dtype=np.float32)
    t_fut = np.arange(1, steps + 1) * dt
    base = np.zeros((n, steps, 2), dtype=np.float32)
    if not n:
        return MoverInputs(feats, patches, base)
    planes = _scene_planes(current, tracks)
    r = PATCH // 2
    padded = np.pad(planes, ((0, 0), (r, r), (r, r)))
    own = np.pad(np.stack([tr.cells for tr in tracks]).astype(np.float32), ((0, 0), (r, r), (r, r)))
    step = np.hypot(*np.diff(hp[:, :2], axis=0).T)  # ego step lengths, metres
    turn = np.diff(np.unwrap(hp[:, 2]))  # ego heading changes, radians
    ego = np.concatenate([step / 5.0, turn * 10.0]).astype(np.float32)
    vs = np.asarray(grid.voxel_size[:2], dtype=np.float64)
    lo = np.asarray(grid.range_min[:2], dtype=np.float64)
    for i, tr in enumerate(tracks):
        rel = np.zeros((h, 2))
        seen = np.zeros(h)
        for t, c in zip(tr.times, tr.centroids):
            k = h - 1 + int(round(t / dt))
            if 0 <= k < h:
                rel[k], seen[k] = c - tr.centroid, 1.0
        ix, iy = np.nonzero(tr.cells)
        cls = np.zeros(len(MOVABLE_CLASS_IDS))
        cls[MOVABLE_CLASS_IDS.index(tr.cls)] = 1.0
        extent = [len(ix) / 10.0, (ix.max() - ix.min() + 1) * vs[0] / 10.0,
                  (iy.max() - iy.min() + 1) * vs[1] / 10.0]  # fmt: skip
        feats[i] = np.concatenate([
            rel.ravel() / 10.0, seen, tr.velocity / 10.0, cls, extent, tr.centroid / 40.0, ego,
        ])  # fmt: skip
        cx, cy = np.floor((tr.centroid - lo) / vs).astype(int)
        cx, cy = np.clip(cx, 0, planes.shape[1] - 1), np.clip(cy, 0, planes.shape[2] - 1)
        patches[i, :-1] = padded[:, cx : cx + PATCH, cy : cy + PATCH]
        patches[i, -1] = own[i, cx : cx + PATCH, cy : cy + PATCH]
        base[i] = t_fut[:, None] * tr.velocity[None]
    return MoverInputs(feats, patches, base)


class MoverHead(nn.Module):
    """Future displacements of tracked movers (module docstring).

    Args:
        history: H history frames.
        steps: S future steps.
        hidden: width of the MLP.
    """

    #: Scale of the residual outputs, metres.
    SCALE = 2.0

    def __init__(self, history: int, steps: int, hidden: int = 128):
        super().__init__()
        if history < 2 or steps < 1:
            raise ValueError(f"history/steps: expected >= 2 / >= 1, got {history}/{steps}")
        self.history, self.steps = history, steps
        self.scene = nn.Sequential(
            nn.Conv2d(CHANNELS, 16, 3, padding=1), nn.GELU(),
            nn.Conv2d(16, 32, 3, stride=2, padding=1), nn.GELU(),
            nn.AdaptiveAvgPool2d(2), nn.Flatten(), nn.Linear(32 * 4, 64), nn.GELU(),
        )  # fmt: skip
        self.mlp = nn.Sequential(
            nn.Linear(feature_size(history) + 64, hidden), nn.GELU(),
            nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, steps * 2),
        )  # fmt: skip
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(
        self, feats: torch.Tensor, patches: torch.Tensor, base: torch.Tensor
    ) -> torch.Tensor:
        """Displacements [N, S, 2] (metres, current ego frame) of N movers.

        Args:
            feats: [N, F]; patches: [N, CHANNELS, PATCH, PATCH]; base: [N, S, 2]
                (:class:`MoverInputs`).
        """
        if feats.shape[0] == 0:
            return base.float()
        x = torch.cat([feats.float(), self.scene(patches.float())], dim=1)
        out = self.mlp(x).view(-1, self.steps, 2)
        return base.float() + self.SCALE * out
