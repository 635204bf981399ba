"""The token interface between the scene tokenizer and the world model.

A tokenizer turns occupancy ``[B, X, Y, Z]`` into discrete codes on a latent grid
``[h, w]`` (bird's-eye view, x then y as in the occupancy grid). A model may use several
codebooks (the AM-VAE uses two: air and non-air); codes of codebook ``g`` index into a
codebook of ``codebook_sizes[g]`` entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["Tokens"]


@dataclass(frozen=True)
class Tokens:
    """Discrete scene tokens.

    Attributes:
        indices: [B, G, h, w] int64 code indices; ``indices[:, g]`` indexes codebook ``g``.
            A sequence of frames is carried as [B, T, G, h, w] by the world model.
        codebook_sizes: length-G tuple of codebook sizes.
        codebook_names: length-G tuple of names (e.g. ``("air", "non_air")`` or ``("scene",)``).
    """

    indices: torch.Tensor
    codebook_sizes: tuple[int, ...]
    codebook_names: tuple[str, ...]

    def __post_init__(self) -> None:
        if not isinstance(self.indices, torch.Tensor) or self.indices.dtype != torch.int64:
            raise TypeError(
                f"indices: expected an int64 tensor, got "
                f"{getattr(self.indices, 'dtype', type(self.indices))}"
            )
        g = len(self.codebook_sizes)
        if len(self.codebook_names) != g:
            raise ValueError(
                f"codebook_names: expected {g} names to match codebook_sizes, "
                f"got {len(self.codebook_names)}"
            )
        if self.indices.dim() < 3 or self.indices.shape[-3] != g:
            raise ValueError(
                f"indices: expected shape [..., {g}, h, w], got {tuple(self.indices.shape)}"
            )

    @property
    def num_codebooks(self) -> int:
        """G."""
        return len(self.codebook_sizes)

    @property
    def grid_shape(self) -> tuple[int, int]:
        """(h, w) of the latent token grid."""
        return tuple(self.indices.shape[-2:])  # type: ignore[return-value]

    def to(self, device: torch.device | str) -> Tokens:
        """Copy onto ``device``."""
        return Tokens(self.indices.to(device), self.codebook_sizes, self.codebook_names)
