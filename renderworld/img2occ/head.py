"""Voxel head: lifted features → one anchor Gaussian per voxel.

The head works in bird's-eye view with the height folded into channels ([B, D·Z, X, Y]) and
2-D convolutions, like OccWorld's tokenizer. Why not 3-D convs: Z is small (4..16) and CPU
2-D convolutions are much faster than 3-D ones of the same receptive field (oneDNN has tuned
2-D kernels; a 3x3x3 conv over 200x200x16 voxels is ~3x the FLOPs of a 3x3 BEV conv with the
same channel budget and far slower per FLOP), while folding keeps every height's features
available to the per-voxel outputs, which are unfolded again from channels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from renderworld.constants import NUM_SEMANTIC_CLASSES
from renderworld.img2occ.config import Img2OccConfig
from renderworld.img2occ.encoder import _norm, _ResBlock

__all__ = ["AnchorGaussians", "GaussianHead", "QUAT_EPS", "NUM_ENCODING_CHANNELS"]

#: Epsilon inside the quaternion normalisation (docs/conventions.md#numerics).
QUAT_EPS = 1e-8
#: Per-voxel encoding channels appended to the lifted features: seen flag, log depth,
#: mean view direction (3), normalised voxel-centre position (3).
NUM_ENCODING_CHANNELS = 8
# Attributes per voxel: offset 3, scale 3, quaternion 4, opacity 1, class logits K.
_NUM_ATTRS = 3 + 3 + 4 + 1 + NUM_SEMANTIC_CLASSES


@dataclass
class AnchorGaussians:
    """One semantic Gaussian per voxel, in the keyframe's ego frame.

    V = X·Y·Z voxels in row-major ``[x, y, z]`` order (``VoxelGrid.flat_index``).

    Attributes:
        means: [B, V, 3] centres, metres (voxel centre + offset bounded by half a voxel).
        quats: [B, V, 4] unit quaternions ``[w, x, y, z]``.
        scales: [B, V, 3] standard deviations along the principal axes, metres, in
            ``[s_min, s_max]``.
        opacities: [B, V] in (0, 1).
        logits: [B, V, K] semantic logits over the K = 17 non-free classes.
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    logits: torch.Tensor


class GaussianHead(nn.Module):
    """BEV convolutional head predicting the anchor Gaussians.

    Args:
        cfg: model config (grid, feature_channels, head_channels, head_blocks,
            scale_range, init_opacity).
    """

    def __init__(self, cfg: Img2OccConfig):
        super().__init__()
        x, y, z = cfg.grid.shape
        self.shape = (x, y, z)
        voxel = torch.tensor(cfg.grid.voxel_size, dtype=torch.float32)
        self.register_buffer("half_voxel", voxel / 2, persistent=False)
        edge = float(voxel.min())
        self.s_min = cfg.scale_range[0] * edge
        self.s_max = cfg.scale_range[1] * edge
        # Depth-aware lifting appends surface mass, occlusion and K class probabilities.
        extra = 2 + NUM_SEMANTIC_CLASSES if cfg.depth_bins else 0
        c_in = (cfg.feature_channels + NUM_ENCODING_CHANNELS + extra) * z
        hid = cfg.head_channels
        self.inp = nn.Sequential(nn.Conv2d(c_in, hid, 1, bias=False), _norm(hid), nn.ReLU())
        self.blocks = nn.Sequential(*[_ResBlock(hid) for _ in range(cfg.head_blocks)])
        self.out = nn.Conv2d(hid, z * _NUM_ATTRS, 1)
        with torch.no_grad():
            self.out.weight.mul_(0.1)  # start near the biases below, not at random shapes
            bias = self.out.bias.view(z, _NUM_ATTRS)
            bias.zero_()
            bias[:, 6] = 1.0  # quaternion w: identity rotation
            p = cfg.init_opacity
            bias[:, 10] = float(torch.logit(torch.tensor(p)))

    def forward(self, voxel_features: torch.Tensor, centres: torch.Tensor) -> AnchorGaussians:
        """Predict Gaussians.

        Args:
            voxel_features: [B, F, X, Y, Z] lifted features and encodings
                (F = feature_channels + NUM_ENCODING_CHANNELS, + 2 + K with depth_bins).
            centres: [V, 3] voxel centres, metres, ego frame.

        Returns:
            :class:`AnchorGaussians`.
        """
        b, f, x, y, z = voxel_features.shape
        if (x, y, z) != self.shape:
            raise ValueError(f"voxel_features: expected grid {self.shape}, got {(x, y, z)}")
        bev = voxel_features.permute(0, 1, 4, 2, 3).reshape(b, f * z, x, y)
        h = self.blocks(self.inp(bev))
        # Float32 from here: the centre offsets, scales and quaternions are geometry that the
        # rasterizer reads in float32 (bf16 would move a centre 40 m out by ~0.2 m).
        raw = self.out(h).float().view(b, z, _NUM_ATTRS, x, y).permute(0, 3, 4, 1, 2)
        raw = raw.reshape(b, x * y * z, _NUM_ATTRS)  # row-major [x, y, z]
        offset = torch.tanh(raw[..., 0:3]) * self.half_voxel
        scales = self.s_min + (self.s_max - self.s_min) * torch.sigmoid(raw[..., 3:6])
        q = raw[..., 6:10]
        quats = q / torch.sqrt((q * q).sum(-1, keepdim=True) + QUAT_EPS)
        opacities = torch.sigmoid(raw[..., 10])
        logits = raw[..., 11:]
        return AnchorGaussians(
            means=centres.to(raw.dtype)[None] + offset,
            quats=quats,
            scales=scales,
            opacities=opacities,
            logits=logits,
        )
