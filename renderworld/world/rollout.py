"""Autoregressive rollout of the world model.

Each step runs the model on the context window, takes the last position's argmax codes (per
codebook) and predicted displacement, and appends them as the next frame. The **current** command is
passed unchanged at every step: a future frame's command is never used (OccWorld feeds the GT future
command during rollout, a leak; docs/reference_numbers.md#occworld). The context keeps at most
``config.max_frames`` frames (the training window length); with the default 5 history frames and 6
steps it never has to drop a frame.

With ``use_cache`` (default) each step computes only the new frame, reusing the attention
keys/values of earlier frames (:class:`renderworld.world.cache.WorldModelCache`), and the code
logits of the last position only (``last_only``: the first step's up-path skips the four
earlier history frames); the reference is ``use_cache=False``, which recomputes the whole
window and every position's logits every step. Once the
context would exceed ``max_frames`` the window slides, positions shift, and the rollout falls
back to recomputing.

The history is validated once (:meth:`WorldModel._check_inputs`); the steps append only the
model's own argmax codes and displacements and skip the per-call checks. The next codes are
the argmax over each cell's logits read in their stored channels-last order (the same values
and first-maximum tie rule as an argmax over the class axis of the returned view, without the
strided reduction). ``trajectory_only`` skips the last step's up-path and code heads: nothing
reads the last frame's codes when the forecast is not decoded.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from renderworld.world.cache import WorldModelCache

__all__ = ["RolloutOutput", "rollout"]


@dataclass
class RolloutOutput:
    """Result of :func:`rollout`.

    Attributes:
        tokens: [B, S, G, h, w] int64 predicted codes of frames t+1..t+S; None for a
            ``trajectory_only`` rollout.
        displacements: [B, S, 2] metres, predicted ``d[t+k-1]`` (frame t+k-1 -> t+k), current
            ego frame.
        trajectory: [B, S, 2] metres, cumulative positions of frames t+1..t+S in the current
            ego frame (``cumsum(displacements)``).
    """

    tokens: torch.Tensor
    displacements: torch.Tensor
    trajectory: torch.Tensor


@torch.no_grad()
def rollout(
    model,
    history_tokens: torch.Tensor,
    history_displacements: torch.Tensor,
    command: torch.Tensor,
    steps: int = 6,
    use_cache: bool = True,
    trajectory_only: bool = False,
) -> RolloutOutput:
    """Forecast ``steps`` frames autoregressively from a history.

    Args:
        model: a :class:`renderworld.world.WorldModel` (its train/eval mode is left as is).
        history_tokens: [B, T, G, h, w] int64 codes of frames t-T+1..t.
        history_displacements: [B, T-1, 2] metres, current ego frame.
        command: [B] int64 index into ``COMMANDS``, held fixed for every step.
        steps: number of future frames S >= 1.
        use_cache: reuse earlier frames' attention keys/values (same result, ~T x less work).
        trajectory_only: skip the last step's code logits (``tokens`` is then None; the
            displacements and trajectory are unchanged).

    Returns:
        :class:`RolloutOutput`.
    """
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if not isinstance(history_tokens, torch.Tensor) or history_tokens.dim() != 5:
        raise ValueError(
            "history_tokens: expected [B, T, G, h, w], got "
            f"{getattr(history_tokens, 'shape', None)}"
        )
    max_frames = model.config.max_frames
    t0 = history_tokens.shape[1]
    if t0 > max_frames:
        raise ValueError(f"history_tokens: expected at most {max_frames} frames, got {t0}")
    model._check_inputs(history_tokens, history_displacements, command)
    tokens = history_tokens
    disps = history_displacements
    cache = WorldModelCache() if use_cache else None
    for step in range(steps):
        if cache is not None and tokens.shape[1] > max_frames:
            cache = None  # the window slides from here on: recompute
        codes = not (trajectory_only and step == steps - 1)
        if cache is not None:
            out = model(tokens, disps, command, cache=cache, last_only=True,
                        with_logits=codes, validate=False)  # fmt: skip
        else:
            ctx = min(tokens.shape[1], max_frames)
            out = model(tokens[:, -ctx:], disps[:, disps.shape[1] - (ctx - 1) :], command,
                        with_logits=codes, validate=False)  # fmt: skip
        disps = torch.cat([disps, out.displacement[:, -1:].to(disps.dtype)], dim=1)
        if codes:  # lg[:, -1] is [B, K, h, w], a view of [B, h, w, K] stored channels-last
            nxt = torch.stack([lg[:, -1].permute(0, 2, 3, 1).argmax(-1) for lg in out.logits], 1)
            tokens = torch.cat([tokens, nxt[:, None]], dim=1)  # [B, T+1, G, h, w]
    future_disp = disps[:, t0 - 1 :]
    return RolloutOutput(
        tokens=None if trajectory_only else tokens[:, t0:],
        displacements=future_disp,
        trajectory=torch.cumsum(future_disp, dim=1),
    )
