"""World-model training loss (paper Eq. 6.20) and teacher-forcing targets.

``L = mean_g CE_g(logits_g, codes_g) + lambda_l2 * L2(cumsum(d_pred), cumsum(d_gt))``:
token cross-entropy per codebook averaged over valid positions and cells, then averaged over
codebooks; L2 = mean over valid positions of the Euclidean distance (metres) between the
cumulative predicted and GT trajectories (accumulated from position ``cumulative_from``;
OccWorld weights CE x1, L2 x0.1).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from renderworld.precision import float32_boundary
from renderworld.world.model import WorldModelOutput

__all__ = ["WorldModelTargets", "teacher_forcing_split", "world_model_loss"]

_EPS = 1e-12


@dataclass
class WorldModelTargets:
    """Targets aligned with :class:`WorldModelOutput` (index i = frame i+1 / ``d[i]``).

    Attributes:
        tokens: [B, T, G, h, w] int64 codes of frames 1..T of the window.
        displacements: [B, T, 2] metres, ``d[0..T-1]``, current ego frame.
        valid: [B, T] bool or None; False where the target frame lies past the scene end.
    """

    tokens: torch.Tensor
    displacements: torch.Tensor
    valid: torch.Tensor | None = None


def teacher_forcing_split(
    tokens: torch.Tensor, displacements: torch.Tensor, valid: torch.Tensor | None = None
) -> tuple[tuple[torch.Tensor, torch.Tensor], WorldModelTargets]:
    """Split a window of L frames into model inputs (frames 0..L-2) and targets (1..L-1).

    Args:
        tokens: [B, L, G, h, w] int64.
        displacements: [B, L-1, 2] metres, ``d[i]`` = frame i -> i+1, current ego frame.
        valid: [B, L] bool frame validity (False past the scene end) or None.

    Returns:
        ((input_tokens [B, L-1, G, h, w], input_displacements [B, L-2, 2]), targets).
    """
    if tokens.dim() != 5 or tokens.shape[1] < 2:
        raise ValueError(f"tokens: expected [B, L>=2, G, h, w], got {tuple(tokens.shape)}")
    b, n = tokens.shape[:2]
    if tuple(displacements.shape) != (b, n - 1, 2):
        raise ValueError(
            f"displacements: expected [{b}, {n - 1}, 2], got {tuple(displacements.shape)}"
        )
    tv = None
    if valid is not None:
        if tuple(valid.shape) != (b, n) or valid.dtype != torch.bool:
            raise ValueError(f"valid: expected bool [{b}, {n}], got {tuple(valid.shape)}")
        tv = valid[:, 1:] & valid[:, :-1]
    inputs = (tokens[:, :-1], displacements[:, :-1])
    return inputs, WorldModelTargets(tokens[:, 1:], displacements, tv)


@float32_boundary  # float32: cumulative trajectory sums in metres and cross-entropies
def world_model_loss(
    outputs: WorldModelOutput,
    targets: WorldModelTargets,
    lambda_l2: float = 0.1,
    cumulative_from: int = 0,
) -> dict[str, torch.Tensor]:
    """Token CE (per codebook, averaged) + ``lambda_l2`` x cumulative-trajectory L2.

    Args:
        outputs: model outputs over T positions.
        targets: :class:`WorldModelTargets` over the same T positions.
        lambda_l2: weight of the trajectory term (>= 0).
        cumulative_from: positions ``>= cumulative_from`` are compared as positions
            accumulated from there (the planned trajectory); earlier positions as single
            displacements. A rollout accumulates from the last history frame, so training
            windows that start with history should pass ``history_frames - 1``; with 0 the
            ego head learns to compensate errors of history positions it never predicts at
            inference.

    Returns:
        dict with ``loss`` (scalar), ``token_ce`` (mean over codebooks), ``token_ce/<g>`` per
        codebook index, ``l2`` (metres). With no valid position every term is 0 (defined, and
        still connected to the graph).
    """
    if not lambda_l2 >= 0:
        raise ValueError(f"lambda_l2: expected >= 0, got {lambda_l2}")
    b, t = outputs.displacement.shape[:2]
    if not isinstance(cumulative_from, int) or not 0 <= cumulative_from < max(t, 1):
        raise ValueError(f"cumulative_from: expected an int in [0, {t}), got {cumulative_from!r}")
    if tuple(targets.tokens.shape[:2]) != (b, t) or targets.tokens.shape[2] != len(outputs.logits):
        raise ValueError(
            f"targets.tokens: expected [{b}, {t}, {len(outputs.logits)}, h, w], "
            f"got {tuple(targets.tokens.shape)}"
        )
    if tuple(targets.displacements.shape) != (b, t, 2):
        raise ValueError(
            f"targets.displacements: expected [{b}, {t}, 2], got "
            f"{tuple(targets.displacements.shape)}"
        )
    valid = targets.valid
    if valid is None:
        valid = torch.ones(b, t, dtype=torch.bool, device=outputs.displacement.device)
    w = valid.to(outputs.displacement.dtype)
    denom = w.sum().clamp_min(1.0)

    result: dict[str, torch.Tensor] = {}
    ces = []
    for g, logits in enumerate(outputs.logits):
        ce = F.cross_entropy(
            logits.flatten(0, 1), targets.tokens[:, :, g].flatten(0, 1), reduction="none"
        )
        ce = (ce.mean(dim=(-2, -1)).view(b, t) * w).sum() / denom
        result[f"token_ce/{g}"] = ce
        ces.append(ce)
    token_ce = torch.stack(ces).mean()

    pred = outputs.displacement * w[..., None]
    gt = targets.displacements.to(pred.dtype) * w[..., None]
    c = cumulative_from
    pred = torch.cat([pred[:, :c], torch.cumsum(pred[:, c:], dim=1)], dim=1)
    gt = torch.cat([gt[:, :c], torch.cumsum(gt[:, c:], dim=1)], dim=1)
    # sqrt(x + eps) - sqrt(eps): Euclidean distance with a finite gradient at 0.
    dist = torch.sqrt(((pred - gt) ** 2).sum(-1) + _EPS) - _EPS**0.5
    l2 = (dist * w).sum() / denom
    result.update(token_ce=token_ce, l2=l2, loss=token_ce + lambda_l2 * l2)
    return result
