"""2D convolutional encoder/decoder over bird's-eye-view occupancy, height folded into channels.

The occupancy ``[B, X, Y, Z]`` (Occ3D class ids) is embedded per voxel with a learned class
embedding ``[B, X, Y, Z, E]`` and the height axis is folded into channels, giving a BEV image
``[B, Z*E, X, Y]``. A residual conv encoder halves the resolution per level down to the latent
grid ``[h, w]`` (optional self-attention there); the decoder mirrors it back to ``[X, Y]`` and
output heads unfold channels into ``[B, X, Y, Z, K]`` per-voxel scores.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from renderworld.constants import NUM_OCC3D_CLASSES
from renderworld.tokenizer.config import TokenizerConfig

__all__ = ["ClassEmbedding", "Encoder", "Decoder", "VoxelHead"]


def _groups(channels: int) -> int:
    """Largest group count <= 32 dividing ``channels`` (GroupNorm)."""
    return next(g for g in (32, 16, 8, 4, 2, 1) if channels % g == 0)


def _norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(_groups(channels), channels, eps=1e-6)


class ResBlock(nn.Module):
    """Pre-activation residual block: (GN, SiLU, conv3x3) x 2 + skip (1x1 when widths differ)."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.norm1, self.conv1 = _norm(c_in), nn.Conv2d(c_in, c_out, 3, padding=1)
        self.norm2, self.conv2 = _norm(c_out), nn.Conv2d(c_out, c_out, 3, padding=1)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class AttnBlock(nn.Module):
    """Single-head self-attention over all cells of a [B, C, h, w] map, residual."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.norm = _norm(channels)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.proj = nn.Conv2d(channels, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).reshape(b, 3, c, h * w).transpose(-1, -2).unbind(1)
        out = F.scaled_dot_product_attention(q.unsqueeze(1), k.unsqueeze(1), v.unsqueeze(1))
        return x + self.proj(out.squeeze(1).transpose(-1, -2).reshape(b, c, h, w))


def _level_strides(cfg: TokenizerConfig) -> list[tuple[int, int]]:
    """Stride per down-sampling stage and axis (2 until that axis reached its latent size)."""
    lx, ly = (int(math.log2(f)) for f in cfg.downsample)
    return [(2 if i < lx else 1, 2 if i < ly else 1) for i in range(cfg.num_levels - 1)]


class ClassEmbedding(nn.Module):
    """Occupancy [B, X, Y, Z] int -> BEV features [B, Z*E, X, Y] (learned class embedding)."""

    def __init__(self, embed_dim: int, num_classes: int = NUM_OCC3D_CLASSES) -> None:
        super().__init__()
        self.embed = nn.Embedding(num_classes, embed_dim)

    def forward(self, occ: torch.Tensor) -> torch.Tensor:
        b, x, y, z = occ.shape
        e = self.embed(occ.long())  # [B, X, Y, Z, E]
        return e.permute(0, 3, 4, 1, 2).reshape(b, z * e.shape[-1], x, y)


class Encoder(nn.Module):
    """BEV features [B, Z*E, X, Y] -> encoder features [B, C_top, h, w].

    ``C_top`` is the channel count of the last level; latent heads (1x1 convs, one per
    codebook) live in the model so variants can choose how many latents they read out.
    """

    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        chs, strides = cfg.level_channels, _level_strides(cfg)
        self.conv_in = nn.Conv2d(cfg.grid_shape[2] * cfg.embed_dim, chs[0], 3, padding=1)
        blocks: list[nn.Module] = []
        for level, c in enumerate(chs):
            blocks += [ResBlock(c, c) for _ in range(cfg.num_res_blocks)]
            if level < len(strides):  # down-sample and widen to the next level
                blocks.append(nn.Conv2d(c, chs[level + 1], 3, stride=strides[level], padding=1))
        c = chs[-1]
        blocks.append(ResBlock(c, c))
        if cfg.attention:
            blocks += [AttnBlock(c), ResBlock(c, c)]
        self.blocks = nn.Sequential(*blocks)
        self.norm_out = _norm(c)
        self.out_channels = c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.silu(self.norm_out(self.blocks(self.conv_in(x))))


class _Upsample(nn.Module):
    def __init__(self, c_in: int, c_out: int, stride: tuple[int, int]) -> None:
        super().__init__()
        self.stride = stride
        self.conv = nn.Conv2d(c_in, c_out, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=self.stride, mode="nearest"))


class Decoder(nn.Module):
    """Quantized latent [B, C_in, h, w] -> decoder features [B, C_0, X, Y] (mirrors Encoder)."""

    def __init__(self, cfg: TokenizerConfig, in_channels: int) -> None:
        super().__init__()
        chs, strides = cfg.level_channels, _level_strides(cfg)
        c = chs[-1]
        self.conv_in = nn.Conv2d(in_channels, c, 3, padding=1)
        blocks: list[nn.Module] = [ResBlock(c, c)]
        if cfg.attention:
            blocks += [AttnBlock(c), ResBlock(c, c)]
        for level in reversed(range(len(chs))):
            blocks += [ResBlock(chs[level], chs[level]) for _ in range(cfg.num_res_blocks)]
            if level > 0:  # up-sample and narrow to the next (finer) level
                blocks.append(_Upsample(chs[level], chs[level - 1], strides[level - 1]))
        c = chs[0]
        self.blocks = nn.Sequential(*blocks)
        self.norm_out = _norm(c)
        self.out_channels = c

    def forward(self, q: torch.Tensor) -> torch.Tensor:
        return F.silu(self.norm_out(self.blocks(self.conv_in(q))))


class VoxelHead(nn.Module):
    """Decoder features [B, D, X, Y] -> per-voxel scores [B, X, Y, Z, K] (1x1 conv, unfolded)."""

    def __init__(self, channels: int, height: int, num_outputs: int) -> None:
        super().__init__()
        self.height, self.num_outputs = height, num_outputs
        self.conv = nn.Conv2d(channels, height * num_outputs, 1)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        b, _, x, y = feats.shape
        out = self.conv(feats).reshape(b, self.height, self.num_outputs, x, y)
        return out.permute(0, 3, 4, 1, 2)
