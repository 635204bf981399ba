"""The temporal world model: scene tokens + ego tokens -> next-frame tokens and ego motion.

Architecture (OccWorld-style, paper Eqs. 6.17-6.18):

1. Each frame's codes (all G codebooks) are embedded and summed, plus a learned spatial and a
   temporal position embedding, plus the frame's ego token broadcast to every cell.
2. Ego token of frame ``i`` = MLP(displacement into frame ``i`` (``d[i-1]``, zero and flagged
   absent for the first frame), one-hot current command). The displacement *out of* frame ``i``
   is what the model predicts there, so it is never an input at ``i`` (causality).
3. U-Net over token maps (h x w -> h/2 -> h/4 ...): at each level causal temporal self-attention
   per cell (:class:`SceneBlock`), stride-2 conv down, nearest-up + skip-concat conv fuse up.
4. At the coarsest level the ego token cross-attends to its own frame's scene cells and runs
   causal attention over time; the ego head gives 3 modes x (dx, dy), one per command, and the
   current command selects the mode (OccWorld). Outputs are bounded by
   ``max_displacement * tanh(raw / max_displacement)``.
5. Per-codebook linear heads on the finest level give next-frame code logits.

Output index ``i`` is the prediction for frame ``i + 1`` (codes) and for ``d[i]`` (the ego
motion from frame ``i`` to ``i + 1``), made from frames ``<= i`` only.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from renderworld.constants import COMMANDS
from renderworld.precision import autocast_off, to_float32
from renderworld.world.blocks import Downsample, EgoTemporalBlock, SceneBlock, UpFuse
from renderworld.world.cache import WorldModelCache
from renderworld.world.config import WorldModelConfig
from renderworld.world.rollout import RolloutOutput, rollout

__all__ = [
    "NUM_EGO_FEATURES",
    "WorldModel",
    "WorldModelCache",
    "WorldModelOutput",
    "ego_features",
]

#: dx, dy (normalised), previous-step-present flag, one-hot command.
NUM_EGO_FEATURES = 3 + len(COMMANDS)


@dataclass
class WorldModelOutput:
    """Predictions of one forward pass over T input frames.

    Attributes:
        logits: G tensors [B, T, K_g, h, w]; index ``i`` scores frame ``i + 1``'s codes.
        displacement: [B, T, 2] metres, current ego frame; index ``i`` predicts ``d[i]``
            (frame ``i`` -> ``i + 1``), the mode of the current command.
        displacement_modes: [B, T, len(COMMANDS), 2] metres, every command's mode.
    """

    logits: list[torch.Tensor]
    displacement: torch.Tensor
    displacement_modes: torch.Tensor


def ego_features(
    displacements: torch.Tensor, command: torch.Tensor, num_frames: int, max_displacement: float
) -> torch.Tensor:
    """Per-frame ego token inputs.

    Args:
        displacements: [B, T-1, 2] metres, ``d[i]`` = frame i -> i+1 in the current ego frame.
        command: [B] int64 index into ``COMMANDS``.
        num_frames: T.
        max_displacement: normalisation, metres.

    Returns:
        [B, T, NUM_EGO_FEATURES]: frame ``i`` carries ``d[i-1] / max_displacement`` and a flag
        1 (zeros and flag 0 for frame 0), and the one-hot command.
    """
    b = command.shape[0]
    prev = torch.zeros(b, num_frames, 3, dtype=displacements.dtype, device=displacements.device)
    prev[:, 1:, :2] = displacements / max_displacement
    prev[:, 1:, 2] = 1.0
    onehot = F.one_hot(command, len(COMMANDS)).to(prev.dtype)
    return torch.cat([prev, onehot[:, None].expand(b, num_frames, -1)], dim=-1)


class WorldModel(nn.Module):
    """Causal multi-scale temporal world model over scene tokens.

    Args:
        config: :class:`WorldModelConfig`.
    """

    def __init__(self, config: WorldModelConfig):
        super().__init__()
        if not isinstance(config, WorldModelConfig):
            raise TypeError(f"config: expected WorldModelConfig, got {type(config).__name__}")
        self.config = config
        d, heads, r = config.embed_dim, config.num_heads, config.mlp_ratio
        h, w = config.token_grid
        self.code_embed = nn.ModuleList(nn.Embedding(k, d) for k in config.codebook_sizes)
        self.pos_spatial = nn.Parameter(torch.randn(h, w, d) * 0.02)
        self.pos_time = nn.Parameter(torch.randn(config.max_frames, d) * 0.02)
        self.ego_in = nn.Sequential(
            nn.Linear(NUM_EGO_FEATURES, d), nn.GELU(), nn.Linear(d, d), nn.LayerNorm(d)
        )
        self.ego_to_scene = nn.Linear(d, d)
        self.enc = nn.ModuleList(
            nn.ModuleList(SceneBlock(d, heads, r) for _ in range(n))
            for n in config.layers_per_scale
        )
        self.down = nn.ModuleList(Downsample(d) for _ in range(config.num_scales - 1))
        self.up = nn.ModuleList(UpFuse(d) for _ in range(config.num_scales - 1))
        self.ego_block = EgoTemporalBlock(d, heads, r)
        self.ego_head = nn.Linear(d, len(COMMANDS) * 2)
        if config.cv_residual:  # start exactly at the constant-velocity prior
            nn.init.zeros_(self.ego_head.weight)
            nn.init.zeros_(self.ego_head.bias)
        self.out_norm = nn.LayerNorm(d)
        self.code_heads = nn.ModuleList(nn.Linear(d, k) for k in config.codebook_sizes)

    # ------------------------------------------------------------------ validation
    def _check_inputs(
        self, tokens: torch.Tensor, displacements: torch.Tensor, command: torch.Tensor
    ) -> None:
        cfg = self.config
        if not isinstance(tokens, torch.Tensor) or tokens.dtype != torch.int64:
            raise TypeError(
                f"tokens: expected an int64 tensor, got {getattr(tokens, 'dtype', tokens)}"
            )
        if tokens.dim() != 5 or tuple(tokens.shape[2:]) != (cfg.num_codebooks, *cfg.token_grid):
            raise ValueError(
                f"tokens: expected [B, T, {cfg.num_codebooks}, {cfg.token_grid[0]}, "
                f"{cfg.token_grid[1]}], got {tuple(tokens.shape)}"
            )
        b, t = tokens.shape[:2]
        if not 1 <= t <= cfg.max_frames:
            raise ValueError(f"tokens: expected 1..{cfg.max_frames} frames, got {t}")
        if not isinstance(displacements, torch.Tensor) or not displacements.is_floating_point():
            raise TypeError("displacements: expected a floating-point tensor")
        if tuple(displacements.shape) != (b, t - 1, 2):
            raise ValueError(
                f"displacements: expected [B, T-1, 2] = [{b}, {t - 1}, 2], "
                f"got {tuple(displacements.shape)}"
            )
        if not isinstance(command, torch.Tensor) or command.dtype != torch.int64:
            raise TypeError(
                f"command: expected an int64 tensor, got {getattr(command, 'dtype', command)}"
            )
        if tuple(command.shape) != (b,):
            raise ValueError(f"command: expected shape [{b}], got {tuple(command.shape)}")
        # The value checks read back in one host sync (each would otherwise wait for the GPU).
        dev = tokens.device
        flags = [
            ((tokens[:, :, g] < 0) | (tokens[:, :, g] >= k)).any()
            for g, k in enumerate(cfg.codebook_sizes)
        ]
        flags.append(~torch.isfinite(displacements).all().to(dev))
        flags.append(((command < 0) | (command >= len(COMMANDS))).any().to(dev))
        bad = torch.stack(flags).tolist()
        for g, k in enumerate(cfg.codebook_sizes):
            if bad[g]:
                codes = tokens[:, :, g]
                raise ValueError(
                    f"tokens: codebook {g} codes must lie in [0, {k}), got "
                    f"[{int(codes.min())}, {int(codes.max())}]"
                )
        if bad[-2]:
            raise ValueError("displacements: expected finite values, got NaN or inf")
        if bad[-1]:
            raise ValueError(f"command: expected indices into {COMMANDS}, got {command.tolist()}")

    # ------------------------------------------------------------------ forward
    def forward(
        self,
        tokens: torch.Tensor,
        displacements: torch.Tensor,
        command: torch.Tensor,
        cache: WorldModelCache | None = None,
        last_only: bool = False,
        *,
        logits_from: int = 0,
        with_logits: bool = True,
        validate: bool = True,
    ) -> WorldModelOutput:
        """Teacher-forced next-frame prediction at every position of a window.

        Args:
            tokens: [B, T, G, h, w] int64 codes of frames 0..T-1 (each in its own ego frame).
            displacements: [B, T-1, 2] metres, ``d[i]`` = ego motion frame i -> i+1 expressed
                in the current ego frame (see :mod:`renderworld.world.config`).
            command: [B] int64 index into ``COMMANDS``: the current command, used for every
                frame of the window.
            cache: None, or a :class:`WorldModelCache` holding frames ``0..F-1`` of these same
                inputs (empty at first): only frames ``F..T-1`` are computed, the outputs cover
                only them, and the cache is extended to T frames. Results equal the uncached
                call's last ``T - F`` positions.
            last_only: compute the code logits of the last position only (``logits`` then
                hold one position, [B, 1, K_g, h, w]); displacements still cover every
                position. The up-path and the code heads feed nothing else, so this skips
                work, not information (the rollout reads only the last position).
            logits_from: compute the code logits of positions ``logits_from .. T-1`` only
                (``logits`` then hold ``T - logits_from`` positions); the same skip for a
                teacher-forced loss that scores only the later positions. Without a cache.
            with_logits: False skips the up-path and the code heads altogether (``logits`` is
                then empty): the displacements do not read them (a trajectory-only rollout's
                last step).
            validate: False skips the input checks (the rollout checks its history once and
                appends only its own argmax codes and predicted displacements).

        Returns:
            :class:`WorldModelOutput` with T (or T - F) predictions (index i predicts frame
            i+1 and d[i]).
        """
        if validate:
            self._check_inputs(tokens, displacements, command)
        cfg = self.config
        b, t = tokens.shape[:2]
        if logits_from and (cache is not None or not 0 < logits_from < t):
            raise ValueError(
                f"logits_from: expected a position in 1..{t - 1} without a cache, got "
                f"{logits_from}" + (" with a cache" if cache is not None else "")
            )
        start = 0
        if cache is not None:
            if not isinstance(cache, WorldModelCache) or not 0 <= cache.frames < t:
                raise ValueError(
                    f"cache: expected a WorldModelCache holding fewer than {t} frames, got "
                    f"{getattr(cache, 'frames', cache)!r}"
                )
            start = cache.frames
            if not cache.scene:
                cache.scene = [[{} for _ in blocks] for blocks in self.enc]
        feats = ego_features(
            displacements.to(self.pos_time.dtype), command, t, cfg.max_displacement
        )
        ego = self.ego_in(feats[:, start:]) + self.pos_time[start:t]
        x = sum(emb(tokens[:, start:, g]) for g, emb in enumerate(self.code_embed))
        x = x + self.pos_spatial + self.pos_time[start:t, None, None]  # [B, T', h, w, D]
        x = x + self.ego_to_scene(ego)[:, :, None, None]
        t = t - start

        skips = []
        for s, blocks in enumerate(self.enc):
            for i, blk in enumerate(blocks):
                x = blk(x, None if cache is None else cache.scene[s][i])
            if s < cfg.num_scales - 1:
                skips.append(x)
                x = self.down[s](x)
        # The ego token reads the coarsest scene map of its own frame.
        ego = self.ego_block(ego, x, None if cache is None else cache.ego)
        if cache is not None:
            cache.frames = start + t
        logits = []
        if with_logits:
            first = t - 1 if last_only else logits_from
            if first:  # the up-path and the heads (per frame) feed only the logits
                x, skips = x[:, first:], [sk[:, first:] for sk in skips]
            for s in reversed(range(cfg.num_scales - 1)):
                x = self.up[s](x, skips[s])
            x = self.out_norm(x)
            logits = [head(x).permute(0, 1, 4, 2, 3) for head in self.code_heads]
        # The trajectory head in float32: bf16 would round displacements of ~10 m by ~4 cm.
        with autocast_off():
            raw = self.ego_head(to_float32(ego)).view(b, t, len(COMMANDS), 2)
        if cfg.cv_residual:
            # Prior for d[i]: the displacement into frame i, d[i-1] (none for frame 0).
            prior = torch.zeros(b, start + t, 2, dtype=raw.dtype, device=raw.device)
            prior[:, 1:] = displacements[:, : start + t - 1].to(raw.dtype)
            raw = raw + prior[:, start:, None, :]
        m = cfg.max_displacement
        modes = m * torch.tanh(raw / m)
        idx = command.view(b, 1, 1, 1).expand(b, t, 1, 2)
        disp = modes.gather(2, idx).squeeze(2)
        return WorldModelOutput(logits=logits, displacement=disp, displacement_modes=modes)

    def rollout(
        self,
        history_tokens: torch.Tensor,
        history_displacements: torch.Tensor,
        command: torch.Tensor,
        steps: int | None = None,
        use_cache: bool = True,
        trajectory_only: bool = False,
    ) -> RolloutOutput:
        """Autoregressive forecast; see :func:`renderworld.world.rollout.rollout`."""
        return rollout(
            self,
            history_tokens,
            history_displacements,
            command,
            steps=self.config.future_frames if steps is None else steps,
            use_cache=use_cache,
            trajectory_only=trajectory_only,
        )
