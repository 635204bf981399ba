"""The scene tokenizer: AM-VAE (Section 6.2.2) and its ablations, selected by ``cfg.variant``.

Formulation implemented here (the paper leaves the details open; this is the exact reading):

1. Input occupancy o [B, X, Y, Z] (Occ3D ids, 17 = free = air). A learned class embedding
   with height folded into channels gives a BEV map [B, Z*E, X, Y]; a shared 2D residual conv
   encoder (the paper says "3D CNN"; height-folded 2D convs as in OccWorld) gives
   f [B, D, h, w].
2. Latents (Eq. 6.8): two-codebook variants read two latents from f with 1x1 heads,
   s_air = H_air(f), s_non_air = H_non_air(f) [B, C, h, w]; one-codebook variants read one,
   s = H(f).
3. Quantization (Eq. 6.9): each latent is replaced cell-wise by its nearest entry of its own
   codebook (C_air, C_non_air of K/2 codes each, or one of K), straight-through gradients,
   commitment ``beta * ||s - sg(s')||^2`` per codebook (Eq. 6.15), EMA codebooks with
   dead-code restarts (``quantizer.py``).
4. Decoding (Eq. 6.10): one decoder trunk D (weights shared) mirrors the encoder.
   ``am_vae`` decodes each quantized latent by itself: the air branch
   ``a = head_air(D(s'_air))`` [B, X, Y, Z] is the logit of "voxel is air"; the non-air branch
   ``n = head_non_air(D(s'_non_air))`` [B, X, Y, Z, 17] are logits over the non-air classes.
5. Combination (Eqs. 6.11-6.13): p(free) = sigmoid(a), p(c) = (1 - sigmoid(a)) softmax(n)_c,
   i.e. o_hat = o_hat_air * mask + o_hat_non_air * (1 - mask) with the soft air mask
   sigmoid(a); decoded occupancy is free where p(free) >= 0.5 (mask = air predicted), else
   argmax_c n_c (``heads.py``).
6. Loss (Eqs. 6.12, 6.14-6.16, 6.19): the air branch is trained with BCE on o'_air = [o free]
   over all voxels, the non-air branch with 17-way CE on non-air voxels only (its modified
   target; on air voxels the air mask decides), Lovász-softmax on the combined 18-way
   probabilities, plus the commitment terms:
   ``L = ce_weight * (BCE + CE_non_air) + lovasz_weight * Lovasz + sum_g beta * commit_g``.

Variants at an equal budget of K code vectors (Table 6.6):

=============  ==========================  =================================  =============
variant        latents / codebooks         decoder input                      output head
=============  ==========================  =================================  =============
``plain``      1, K codes ("scene")        s'                                 18-way softmax
``air_mask``   1, K codes ("scene")        s' (both branches from one trunk)  air mask
``separate``   2, K/2 each (air, non_air)  concat(s'_air, s'_non_air)         18-way softmax
``am_vae``     2, K/2 each (air, non_air)  D(s'_air) -> air, D(s'_non_air)    air mask
=============  ==========================  =================================  =============
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer.backbone import ClassEmbedding, Decoder, Encoder, VoxelHead
from renderworld.tokenizer.config import TokenizerConfig
from renderworld.tokenizer.heads import NON_AIR_IDS, combine_air_mask, scores_to_occupancy
from renderworld.tokenizer.losses import air_mask_head_loss, softmax_head_loss
from renderworld.tokenizer.quantizer import VectorQuantizer
from renderworld.tokenizer.tokens import Tokens

__all__ = ["SceneTokenizer", "TokenizerOutput", "build_tokenizer"]

_OCC_DTYPES = (torch.uint8, torch.int16, torch.int32, torch.int64)


@dataclass
class TokenizerOutput:
    """What :meth:`SceneTokenizer.forward` returns.

    Attributes:
        logits: [B, X, Y, Z, 18] class scores (log-probabilities for air-mask heads).
        tokens: The codes of the input.
        loss: Scalar total loss (reconstruction + commitment); None if not computed.
        losses: Detached scalar terms: ``total, recon, ce, lovasz, commit`` (+ ``air,
            non_air`` for air-mask heads).
        stats: Detached scalar codebook health per codebook name: ``<name>/usage`` (batch),
            ``<name>/perplexity``, ``<name>/window_usage``, ``<name>/restarted``.
    """

    logits: torch.Tensor
    tokens: Tokens
    loss: torch.Tensor | None
    losses: dict[str, torch.Tensor] = field(default_factory=dict)
    stats: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def logs(self) -> dict[str, torch.Tensor]:
        """Everything to log, ``loss/<term>`` and ``codebook/<name>/<stat>``."""
        out = {f"loss/{k}": v for k, v in self.losses.items()}
        out.update({f"codebook/{k}": v for k, v in self.stats.items()})
        return out


class SceneTokenizer(nn.Module):
    """Occupancy <-> discrete BEV tokens (see the module docstring for the formulation).

    Args:
        cfg: A validated :class:`TokenizerConfig`.
    """

    def __init__(self, cfg: TokenizerConfig) -> None:
        super().__init__()
        if not isinstance(cfg, TokenizerConfig):
            raise TypeError(f"cfg: expected a TokenizerConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        c = cfg.latent_channels
        self.embed = ClassEmbedding(cfg.embed_dim)
        self.encoder = Encoder(cfg)
        self.latent_heads = nn.ModuleList(
            nn.Conv2d(self.encoder.out_channels, c, 1) for _ in range(cfg.num_codebooks)
        )
        self.quantizers = nn.ModuleList(
            VectorQuantizer(
                k,
                c,
                beta=cfg.beta,
                ema=cfg.ema,
                decay=cfg.ema_decay,
                dead_code_steps=cfg.dead_code_steps,
                usage_window=cfg.usage_window,
            )
            for k in cfg.codebook_sizes
        )
        self.decoder = Decoder(cfg, c * cfg.num_codebooks if cfg.variant == "separate" else c)
        d, z = self.decoder.out_channels, cfg.grid_shape[2]
        if cfg.air_mask_head:
            self.air_head = VoxelHead(d, z, 1)
            self.non_air_head = VoxelHead(d, z, len(NON_AIR_IDS))
        else:
            self.class_head = VoxelHead(d, z, NUM_OCC3D_CLASSES)
        cw = cfg.class_weights
        self.register_buffer(
            "class_weights",
            torch.tensor(cw, dtype=torch.float32) if cw is not None else None,
            persistent=False,
        )

    @torch.no_grad()
    def init_output_prior(self, class_counts: torch.Tensor) -> None:
        """Start the output heads at the data's class frequencies (their biases).

        Each height level's scores start at the log of its classes' frequencies (Laplace
        smoothed: a class never seen starts some 12 nats down instead of level with the rest),
        the air-mask head's air logit at the logit of its free fraction. Where a short schedule
        ends then depends less on the seed: a rare class is not predicted by chance early on,
        and one the data never holds is not predicted at all.

        Args:
            class_counts: [Z, 18] voxel counts per height level and Occ3D class.

        Raises:
            ValueError: naming ``class_counts`` on a wrong shape or negative counts.
        """
        z = self.cfg.grid_shape[2]
        counts = torch.as_tensor(class_counts, dtype=torch.float64)
        if tuple(counts.shape) != (z, NUM_OCC3D_CLASSES) or bool((counts < 0).any()):
            raise ValueError(
                f"class_counts: expected [{z}, {NUM_OCC3D_CLASSES}] non-negative counts, got "
                f"{tuple(counts.shape)}"
            )
        counts = counts + 1.0
        if self.cfg.air_mask_head:
            free = counts[:, FREE_ID]
            occupied = counts.sum(1) - free
            self.air_head.conv.bias.copy_(torch.log(free / occupied).float())
            non_air = counts[:, list(NON_AIR_IDS)]
            prior = torch.log(non_air / non_air.sum(1, keepdim=True))
            self.non_air_head.conv.bias.copy_(prior.reshape(-1).float())
        else:
            prior = torch.log(counts / counts.sum(1, keepdim=True))
            self.class_head.conv.bias.copy_(prior.reshape(-1).float())

    # ------------------------------------------------------------------ validation
    def _check_occ(self, occ: torch.Tensor) -> torch.Tensor:
        if not isinstance(occ, torch.Tensor):
            raise TypeError(f"occ: expected a torch.Tensor, got {type(occ).__name__}")
        if occ.dtype not in _OCC_DTYPES:
            raise TypeError(f"occ: expected an integer tensor (uint8/int64), got {occ.dtype}")
        expected = tuple(self.cfg.grid_shape)
        if occ.dim() != 4 or tuple(occ.shape[1:]) != expected:
            raise ValueError(f"occ: expected shape [B, {expected}], got {tuple(occ.shape)}")
        lo, hi = torch.aminmax(occ)
        lo, hi = int(lo), int(hi)  # one host sync (aminmax), not two
        if lo < 0 or hi >= NUM_OCC3D_CLASSES:
            raise ValueError(
                f"occ: expected Occ3D class ids in [0, {NUM_OCC3D_CLASSES - 1}], "
                f"got range [{lo}, {hi}]"
            )
        return occ.long()

    def _check_tokens(self, tokens: Tokens) -> torch.Tensor:
        if not isinstance(tokens, Tokens):
            raise TypeError(f"tokens: expected Tokens, got {type(tokens).__name__}")
        cfg = self.cfg
        if tuple(tokens.codebook_sizes) != cfg.codebook_sizes or tuple(
            tokens.codebook_names
        ) != tuple(cfg.codebook_names):
            raise ValueError(
                f"tokens: expected codebooks {cfg.codebook_names} of sizes {cfg.codebook_sizes},"
                f" got {tokens.codebook_names} of sizes {tokens.codebook_sizes}"
            )
        if tokens.grid_shape != tuple(cfg.latent_shape):
            raise ValueError(
                f"tokens: expected a latent grid {tuple(cfg.latent_shape)}, got {tokens.grid_shape}"
            )
        idx = tokens.indices
        sizes = torch.tensor(cfg.codebook_sizes, device=idx.device).view(-1, 1, 1)
        if idx.numel() and bool(((idx < 0) | (idx >= sizes)).any()):
            raise ValueError(f"tokens: indices outside [0, {cfg.codebook_sizes}) per codebook")
        return idx

    # ------------------------------------------------------------------ building blocks
    def _latents(self, occ: torch.Tensor) -> list[torch.Tensor]:
        f = self.encoder(self.embed(occ))
        return [head(f) for head in self.latent_heads]

    def _scores(self, q: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        """Quantized latents (one [B, C, h, w] per codebook) -> head outputs."""
        variant = self.cfg.variant
        if variant == "am_vae":
            b = q[0].shape[0]
            feats = self.decoder(torch.cat(q, dim=0))  # shared trunk, each latent on its own
            air_logit = self.air_head(feats[:b])[..., 0]
            non_air = self.non_air_head(feats[b:])
        else:
            feats = self.decoder(torch.cat(q, dim=1) if variant == "separate" else q[0])
            if variant == "plain" or variant == "separate":
                return {"logits": self.class_head(feats)}
            air_logit, non_air = self.air_head(feats)[..., 0], self.non_air_head(feats)
        return {
            "logits": combine_air_mask(air_logit, non_air),
            "air_logit": air_logit,
            "non_air_logits": non_air,
        }

    def _make_tokens(self, indices: list[torch.Tensor]) -> Tokens:
        return Tokens(torch.stack(indices, dim=1), self.cfg.codebook_sizes, self.cfg.codebook_names)

    # ------------------------------------------------------------------ public API
    def forward(self, occ: torch.Tensor, compute_loss: bool = True) -> TokenizerOutput:
        """Encode, quantize, decode and (optionally) score the reconstruction of ``occ``.

        Args:
            occ: [B, X, Y, Z] uint8/int64 Occ3D ids (X, Y, Z = ``cfg.grid_shape``).
            compute_loss: Also compute the loss against ``occ``.

        Returns:
            A :class:`TokenizerOutput`. In training mode the quantizers update their EMA
            codebooks and usage counters and restart dead codes.
        """
        target = self._check_occ(occ)
        qouts = [quant(z) for quant, z in zip(self.quantizers, self._latents(target))]
        heads = self._scores([qo.quantized for qo in qouts])
        tokens = self._make_tokens([qo.indices for qo in qouts])
        stats = {}
        for name, qo in zip(self.cfg.codebook_names, qouts):
            stats.update({f"{name}/{k}": v.detach() for k, v in qo.stats.items()})
        if not compute_loss:
            return TokenizerOutput(heads["logits"], tokens, None, {}, stats)
        cfg = self.cfg
        kw = dict(
            class_weights=self.class_weights,
            ce_weight=cfg.ce_weight,
            lovasz_weight=cfg.lovasz_weight,
            present_only=cfg.lovasz_present_only,
        )
        if cfg.air_mask_head:
            terms = air_mask_head_loss(
                heads["air_logit"], heads["non_air_logits"], heads["logits"], target, **kw
            )
        else:
            terms = softmax_head_loss(heads["logits"], target, **kw)
        commit = torch.stack([qo.loss for qo in qouts]).sum()
        total = terms["recon"] + commit
        losses = {k: v.detach() for k, v in terms.items()}
        losses.update(total=total.detach(), commit=commit.detach())
        return TokenizerOutput(heads["logits"], tokens, total, losses, stats)

    def encode(self, occ: torch.Tensor) -> Tokens:
        """Occupancy [B, X, Y, Z] -> :class:`Tokens` with indices [B, G, h, w] int64.

        Pure assignment: never updates codebooks or usage counters (even in training mode).
        """
        target = self._check_occ(occ)
        idx = [quant.assign(z) for quant, z in zip(self.quantizers, self._latents(target))]
        return self._make_tokens(idx)

    def decode_logits(self, tokens: Tokens) -> torch.Tensor:
        """Tokens with indices [..., G, h, w] -> class scores [..., X, Y, Z, 18].

        Scores are logits (softmax heads) or log-probabilities (air-mask heads).
        """
        idx = self._check_tokens(tokens)
        lead = idx.shape[:-3]
        flat = idx.reshape(-1, *idx.shape[-3:])
        q = [quant.lookup(flat[:, g]) for g, quant in enumerate(self.quantizers)]
        logits = self._scores(q)["logits"]
        return logits.reshape(*lead, *logits.shape[1:])

    def predict(self, logits: torch.Tensor) -> torch.Tensor:
        """Class scores [..., 18] -> occupancy [...] uint8 by this variant's decision rule."""
        return scores_to_occupancy(logits, self.cfg.air_mask_head)

    def decode(self, tokens: Tokens) -> torch.Tensor:
        """Tokens with indices [..., G, h, w] -> occupancy [..., X, Y, Z] uint8 Occ3D ids."""
        return self.predict(self.decode_logits(tokens))

    def num_parameters(self) -> int:
        """Trainable parameter count (EMA codebooks are buffers and not counted)."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)


def build_tokenizer(cfg: TokenizerConfig | dict) -> SceneTokenizer:
    """Build a tokenizer from a config (or a plain dict of its fields, e.g. from Hydra).

    Raises:
        ValueError: on an unknown field or an invalid value (naming the field).
    """
    if isinstance(cfg, dict):
        known = set(TokenizerConfig.__dataclass_fields__)
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ValueError(f"cfg: unknown tokenizer fields {unknown}; expected {sorted(known)}")
        cfg = TokenizerConfig(**cfg)
    return SceneTokenizer(cfg)
