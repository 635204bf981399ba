"""Image encoder: a small residual CNN with an FPN-like top-down merge (or a local timm model).

Down-sampling convolutions use kernel 4, stride 2, padding 1, so feature pixel j of a stride-s
map is centred exactly on input coordinate (j + 0.5)·s: the pixel-area convention of
docs/conventions.md#pixels survives the encoder and the lifting can scale intrinsics by 1/s.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from renderworld.img2occ.config import Img2OccConfig

__all__ = ["ImageEncoder", "IMAGENET_MEAN", "IMAGENET_STD"]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _norm(channels: int) -> nn.GroupNorm:
    # GroupNorm, not BatchNorm: batches are a handful of images of one scene, and the model
    # must behave the same in train and eval (one-sample overfitting, export).
    groups = math.gcd(channels, 8)
    return nn.GroupNorm(groups, channels)


class _ResBlock(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.norm1 = _norm(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.norm2 = _norm(channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        return F.relu(x + self.norm2(self.conv2(y)))


class _Stage(nn.Sequential):
    def __init__(self, c_in: int, c_out: int):
        super().__init__(
            nn.Conv2d(c_in, c_out, 4, stride=2, padding=1, bias=False),
            _norm(c_out),
            nn.ReLU(inplace=True),
            _ResBlock(c_out),
        )


class _TimmTrunk(nn.Module):
    """A timm ``features_only`` model loaded from a local state-dict file."""

    def __init__(self, name: str, weights: str | None):
        super().__init__()
        try:
            import timm
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                f"timm_backbone={name!r} needs the optional package timm (pip install timm)"
            ) from exc
        self.model = timm.create_model(name, pretrained=False, features_only=True)
        if weights is not None:
            path = Path(weights)
            if not path.is_file():
                raise ValueError(f"timm_weights: file not found: {path}")
            state = torch.load(path, map_location="cpu", weights_only=True)
            missing, _ = self.model.load_state_dict(state, strict=False)
            if missing:
                raise ValueError(
                    f"timm_weights: {path} lacks {len(missing)} backbone tensors, "
                    f"e.g. {missing[:3]}"
                )
        self.channels = list(self.model.feature_info.channels())
        self.strides = list(self.model.feature_info.reduction())

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        return list(self.model(x))


class ImageEncoder(nn.Module):
    """Multi-camera image features at 1/``feature_stride`` of the input.

    Args:
        cfg: the model config (encoder_channels, feature_stride, feature_channels, timm_*).

    Input ``images`` [N, 3, H_in, W_in] in [0, 1] (N = B·C); output [N, D, H_in/s, W_in/s].
    """

    def __init__(self, cfg: Img2OccConfig):
        super().__init__()
        self.stride = cfg.feature_stride
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if cfg.timm_backbone is not None:
            self.trunk = _TimmTrunk(cfg.timm_backbone, cfg.timm_weights)
            channels, strides = self.trunk.channels, self.trunk.strides
        else:
            widths = cfg.encoder_channels
            stages, c_in = [], 3
            for c in widths:
                stages.append(_Stage(c_in, c))
                c_in = c
            self.trunk = nn.ModuleList(stages)
            channels = list(widths)
            strides = [2 ** (i + 1) for i in range(len(widths))]
        self._fine_channels = int(channels[0])
        self.fine_stride = int(strides[0])
        if self.stride not in strides:
            raise ValueError(
                f"feature_stride: the encoder has stages at strides {strides}, got {self.stride}"
            )
        # FPN: laterals for the output stage and every deeper one, merged top-down.
        self.used = [i for i, s in enumerate(strides) if s >= self.stride]
        d = cfg.feature_channels
        self.laterals = nn.ModuleList(nn.Conv2d(channels[i], d, 1) for i in self.used)
        self.smooth = nn.Sequential(
            nn.Conv2d(d, d, 3, padding=1, bias=False), _norm(d), nn.ReLU(inplace=True)
        )
        self.out = nn.Conv2d(d, d, 1)

    @property
    def fine_channels(self) -> int:
        """Channels of the first-stage map (stride ``fine_stride``) that
        ``forward(..., return_fine=True)`` also gives."""
        return self._fine_channels

    def forward(self, images: torch.Tensor, return_fine: bool = False):
        """Encode images.

        Args:
            images: [N, 3, H_in, W_in] float in [0, 1].
            return_fine: also return the first stage's features (stride ``fine_stride``).

        Returns:
            [N, D, H_in / stride, W_in / stride] features; with ``return_fine`` the tuple
            ``(features, fine [N, fine_channels, H_in / fine_stride, W_in / fine_stride])``.
        """
        x = (images - self.mean) / self.std
        if isinstance(self.trunk, nn.ModuleList):
            feats = []
            for stage in self.trunk:
                x = stage(x)
                feats.append(x)
        else:
            feats = self.trunk(x)
        merged = None
        for lateral, i in zip(reversed(self.laterals), reversed(self.used)):
            y = lateral(feats[i])
            if merged is not None:
                up = F.interpolate(merged, size=y.shape[-2:], mode="bilinear", align_corners=False)
                y = y + up
            merged = y
        out = self.out(self.smooth(merged))
        return (out, feats[0]) if return_fine else out
