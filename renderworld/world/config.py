"""Configuration of the temporal world model.

Conventions (docs/conventions.md#ego-motion-and-the-command, shared with
:mod:`renderworld.planning`):

* Frames are keyframes at 2 Hz. A window holds frames ``0..T-1``; the world model sees
  ``history_frames`` frames (t-4..t) and rolls out ``future_frames`` (t+1..t+6).
* ``displacements[i]`` (metres, [.., 2] = (dx, dy)) is the ego motion from frame ``i`` to frame
  ``i + 1``: ``p[i + 1] - p[i]`` where ``p[k]`` is the ego origin (rear axle) of frame ``k``
  expressed in the **current** ego frame (the last history frame; x forward, y left). This is
  VAD's per-step offset convention, so the planned trajectory is exactly the
  cumulative sum of the predicted displacements. Occupancy/tokens of each frame stay in that
  frame's own ego frame (as Occ3D stores them).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

from renderworld.constants import FUTURE_FRAMES, HISTORY_FRAMES

__all__ = ["WorldModelConfig"]


@dataclass(frozen=True)
class WorldModelConfig:
    """Hyper-parameters of :class:`renderworld.world.WorldModel`.

    Attributes:
        codebook_sizes: K_g per codebook, in the tokenizer's order (G = len).
        token_grid: (h, w) of the tokenizer's latent grid.
        embed_dim: D, channels at every scale.
        num_heads: attention heads (must divide ``embed_dim``).
        num_scales: U-Net levels; level ``s`` has the token map down-sampled ``s`` times by 2
            (e.g. 50x50 -> 25x25 -> 13x13).
        layers_per_scale: temporal blocks at each level (length ``num_scales``).
        history_frames: frames of history the planner feeds (t-4..t).
        future_frames: frames rolled out (t+1..t+6).
        max_displacement: bound (metres per 0.5 s step) on each predicted displacement
            component, applied with a scaled tanh so rollouts stay bounded; also the input
            normalisation of displacements.
        mlp_ratio: hidden width of the block MLPs relative to ``embed_dim``.
        cv_residual: the ego head predicts a correction to the constant-velocity prior (the
            previous step's displacement) instead of the displacement itself; the head starts
            at zero, so an untrained model plans like constant velocity.
    """

    codebook_sizes: tuple[int, ...] = (512, 512)
    token_grid: tuple[int, int] = (50, 50)
    embed_dim: int = 128
    num_heads: int = 4
    num_scales: int = 3
    layers_per_scale: tuple[int, ...] = (2, 2, 2)
    history_frames: int = HISTORY_FRAMES
    future_frames: int = FUTURE_FRAMES
    max_displacement: float = 15.0
    mlp_ratio: float = 2.0
    cv_residual: bool = True

    def __post_init__(self) -> None:
        # Accept lists (e.g. from a loaded dict) but store tuples so the config stays hashable.
        object.__setattr__(self, "codebook_sizes", tuple(int(k) for k in self.codebook_sizes))
        object.__setattr__(self, "token_grid", tuple(int(k) for k in self.token_grid))
        object.__setattr__(self, "layers_per_scale", tuple(int(k) for k in self.layers_per_scale))
        if len(self.codebook_sizes) == 0 or min(self.codebook_sizes) < 2:
            raise ValueError(
                f"codebook_sizes: expected one or more sizes >= 2, got {self.codebook_sizes}"
            )
        if len(self.token_grid) != 2 or min(self.token_grid) < 1:
            raise ValueError(f"token_grid: expected (h, w) positive, got {self.token_grid}")
        if self.embed_dim < 1 or self.num_heads < 1 or self.embed_dim % self.num_heads:
            raise ValueError(
                f"embed_dim: expected a positive multiple of num_heads={self.num_heads}, "
                f"got {self.embed_dim}"
            )
        if self.num_scales < 1:
            raise ValueError(f"num_scales: expected >= 1, got {self.num_scales}")
        if 2 ** (self.num_scales - 1) > min(self.token_grid):
            raise ValueError(
                f"num_scales: {self.num_scales} levels need a token grid of at least "
                f"{2 ** (self.num_scales - 1)} per side, got {self.token_grid}"
            )
        if len(self.layers_per_scale) != self.num_scales or min(self.layers_per_scale) < 1:
            raise ValueError(
                f"layers_per_scale: expected {self.num_scales} counts >= 1, "
                f"got {self.layers_per_scale}"
            )
        if self.history_frames < 1 or self.future_frames < 1:
            raise ValueError(
                f"history_frames/future_frames: expected >= 1, got "
                f"{self.history_frames}/{self.future_frames}"
            )
        if not self.max_displacement > 0:
            raise ValueError(f"max_displacement: expected > 0 m, got {self.max_displacement}")
        if not self.mlp_ratio > 0:
            raise ValueError(f"mlp_ratio: expected > 0, got {self.mlp_ratio}")

    @property
    def num_codebooks(self) -> int:
        """G."""
        return len(self.codebook_sizes)

    @property
    def max_frames(self) -> int:
        """Longest input window: history + future - 1 (the last future frame is only a target)."""
        return self.history_frames + self.future_frames - 1

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of builtins (tuples as lists), safe for ``torch.load(weights_only=True)``."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> WorldModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        if not isinstance(data, dict):
            raise TypeError(f"data: expected a dict, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"data: unknown WorldModelConfig keys {unknown}")
        return cls(**data)
