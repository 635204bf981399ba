"""The world model's key/value cache, shared by the model and the rollout.

Lives in its own module so :mod:`renderworld.world.model` (which runs the rollout) and
:mod:`renderworld.world.rollout` (which creates caches) both import it without importing each
other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["WorldModelCache"]


@dataclass
class WorldModelCache:
    """Keys/values of the frames already processed (the rollout's KV cache).

    Attributes:
        frames: number of leading frames whose features are cached.
        scene: per scale, per block, the attention cache dict of that
            :class:`renderworld.world.blocks.SceneBlock`.
        ego: the cache dict of the ego temporal attention.
    """

    frames: int = 0
    scene: list = field(default_factory=list)
    ego: dict = field(default_factory=dict)
