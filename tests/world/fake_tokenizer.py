"""A small deterministic stand-in tokenizer satisfying the ``encode``/``decode`` interface.

Not the AM-VAE: each p x p BEV patch becomes
* ``non_air`` code: the most frequent non-free class in the patch (0..16), or 17 if all free;
* ``air`` code (G=2 only): the number of z levels of the patch holding any non-free voxel.
Decoding fills the patch's lowest ``air`` levels (all levels for G=1) with the class
``round(class_of_code[code])`` - a parameter, so state dicts matter for round-trip tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer.tokens import Tokens


@dataclass(frozen=True)
class PatchTokenizerConfig:
    grid_shape: tuple[int, int, int] = (8, 8, 4)
    patch: int = 2
    num_codebooks: int = 2


class PatchTokenizer(nn.Module):
    def __init__(self, config: PatchTokenizerConfig | None = None, **kwargs):
        super().__init__()
        if config is None:
            kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in kwargs.items()}
            config = PatchTokenizerConfig(**kwargs)
        self.config = config
        x, y, z = config.grid_shape
        assert x % config.patch == 0 and y % config.patch == 0
        self.token_grid = (x // config.patch, y // config.patch)
        self.class_of_code = nn.Parameter(
            torch.arange(NUM_OCC3D_CLASSES, dtype=torch.float32), requires_grad=False
        )
        if config.num_codebooks == 2:
            self.codebook_sizes = (z + 1, NUM_OCC3D_CLASSES)
            self.codebook_names = ("air", "non_air")
        else:
            self.codebook_sizes = (NUM_OCC3D_CLASSES,)
            self.codebook_names = ("scene",)

    @classmethod
    def from_config(cls, data: dict) -> PatchTokenizer:
        return cls(**data)

    def encode(self, occ: torch.Tensor) -> Tokens:
        b, nx, ny, nz = occ.shape
        p = self.config.patch
        h, w = self.token_grid
        occ = occ.long()
        ix = torch.arange(nx, device=occ.device) // p
        iy = torch.arange(ny, device=occ.device) // p
        cell = (ix[:, None] * w + iy[None, :])[None, :, :, None].expand(b, nx, ny, nz)
        bidx = torch.arange(b, device=occ.device)[:, None, None, None].expand_as(cell)
        flat = ((bidx * h * w + cell) * NUM_OCC3D_CLASSES + occ).reshape(-1)
        counts = torch.bincount(flat, minlength=b * h * w * NUM_OCC3D_CLASSES)
        counts = counts.view(b, h, w, NUM_OCC3D_CLASSES)
        non_free = counts[..., :FREE_ID]
        cls = torch.where(
            non_free.sum(-1) > 0, non_free.argmax(-1), torch.full_like(non_free[..., 0], FREE_ID)
        )
        codes = [cls]
        if self.config.num_codebooks == 2:
            occ_any = (occ != FREE_ID).view(b, h, p, w, p, nz).any(4).any(2)  # [b,h,w,nz]
            codes = [occ_any.sum(-1), cls]
        idx = torch.stack(codes, dim=1).long()
        return Tokens(idx, self.codebook_sizes, self.codebook_names)

    def decode(self, tokens: Tokens) -> torch.Tensor:
        idx = tokens.indices
        b = idx.shape[0]
        nx, ny, nz = self.config.grid_shape
        p = self.config.patch
        cls_code = idx[:, -1]
        cls = self.class_of_code.round().long().clamp(0, FREE_ID)[cls_code]  # [b,h,w]
        if self.config.num_codebooks == 2:
            levels = idx[:, 0]
        else:
            levels = torch.full_like(cls, nz)
        z = torch.arange(nz, device=idx.device)
        filled = z[None, None, None, :] < levels[..., None]  # [b,h,w,nz]
        vox = torch.where(filled, cls[..., None], torch.full_like(cls[..., None], FREE_ID))
        vox = vox.repeat_interleave(p, dim=1).repeat_interleave(p, dim=2)
        return vox.to(torch.uint8).view(b, nx, ny, nz)
