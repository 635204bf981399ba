"""Scene tokenizers: AM-VAE (air / non-air codebooks), a plain VQ-VAE and their ablations.

Public API::

    cfg = TokenizerConfig(variant="am_vae", grid_shape=(200, 200, 16), latent_shape=(50, 50))
    model = build_tokenizer(cfg)
    out = model(occ)                      # TokenizerOutput(logits, tokens, loss, losses, stats)
    tokens = model.encode(occ)            # Tokens, indices [B, G, h, w] int64
    occ_hat = model.decode(tokens)        # [B, X, Y, Z] uint8
    scores = model.decode_logits(tokens)  # [B, X, Y, Z, 18]
    reconstruction_metrics(occ_hat, occ)  # {"miou", "iou", "per_class_iou", ...}
"""

from renderworld.tokenizer.am_vae import SceneTokenizer, TokenizerOutput, build_tokenizer
from renderworld.tokenizer.config import VARIANTS, TokenizerConfig
from renderworld.tokenizer.fit import fit
from renderworld.tokenizer.heads import NON_AIR_IDS, combine_air_mask, scores_to_occupancy
from renderworld.tokenizer.lovasz import lovasz_softmax, lovasz_softmax_reference
from renderworld.tokenizer.metrics import (
    ConfusionMeter,
    confusion_matrix,
    metrics_from_confusion,
    reconstruction_metrics,
)
from renderworld.tokenizer.quantizer import VectorQuantizer, code_usage_stats
from renderworld.tokenizer.tokens import Tokens

__all__ = [
    "Tokens",
    "TokenizerConfig",
    "VARIANTS",
    "SceneTokenizer",
    "TokenizerOutput",
    "build_tokenizer",
    "VectorQuantizer",
    "code_usage_stats",
    "lovasz_softmax",
    "lovasz_softmax_reference",
    "NON_AIR_IDS",
    "combine_air_mask",
    "scores_to_occupancy",
    "confusion_matrix",
    "metrics_from_confusion",
    "reconstruction_metrics",
    "ConfusionMeter",
    "fit",
]
