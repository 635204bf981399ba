"""Building blocks of the world model: causal temporal attention per token cell.

Scene features are carried channels-last as ``[B, T, h, w, D]``. Every spatial operation
(depth-wise conv, down/up-sampling) acts on one frame at a time and every temporal operation
is causally masked, so the features of frame ``i`` never depend on frames ``> i``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "CausalSelfAttention",
    "CrossAttention",
    "Downsample",
    "EgoTemporalBlock",
    "Mlp",
    "SceneBlock",
    "UpFuse",
    "causal_attention_reference",
    "short_causal_attention",
]


#: Longest key sequence (frames) whose several-query inference runs
#: :func:`short_causal_attention`.
SHORT_SEQUENCE = 32


def causal_attention_reference(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Causal attention of T new positions that follow ``past`` cached ones (fused kernel).

    Args:
        q: [N, heads, T, hd] queries of positions ``past .. past + T - 1``.
        k: [N, heads, past + T, hd] keys of positions ``0 .. past + T - 1``.
        v: [N, heads, past + T, hd] values, same positions.

    Returns:
        [N, heads, T, hd]: new position ``j`` attends to every key up to ``past + j``.
    """
    t, total = q.shape[2], k.shape[2]
    if total == t:
        return F.scaled_dot_product_attention(q, k, v, is_causal=True)
    if t == 1:
        return F.scaled_dot_product_attention(q, k, v)  # the newest position sees all
    keys = torch.arange(total, device=q.device)
    mask = keys[None, :] <= (total - t + torch.arange(t, device=q.device))[:, None]
    return F.scaled_dot_product_attention(q, k, v, attn_mask=mask)


def short_causal_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """:func:`causal_attention_reference` as two batched matrix products and a masked softmax.

    For the several-frame prefix of a rollout on a CPU (the five history frames, every cell at
    once), where the fused kernel takes ~4x longer (the 5-frame prefix at 50x50 cells,
    [2500, 4, 5, 32]: 23-36 ms against ~5 ms, 2 threads, docs/planner.md); one new frame
    over the cached ones stays with the fused kernel, which is as fast. Same inputs, outputs
    and masking as the reference twin; sums run in another order (~1e-6, tested).
    """
    t, total, hd = q.shape[2], k.shape[2], q.shape[-1]
    scores = torch.matmul(q, k.transpose(-1, -2)).mul_(hd**-0.5)  # [N, heads, T, total]
    hidden = torch.ones(t, total, dtype=torch.bool, device=q.device).triu_(total - t + 1)
    return torch.matmul(scores.masked_fill_(hidden, float("-inf")).softmax(-1), v)


class Mlp(nn.Module):
    """Two-layer GELU MLP on the last dimension."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class CausalSelfAttention(nn.Module):
    """Multi-head self-attention over the sequence axis with a causal mask.

    Input/output [N, T, D]: position ``i`` attends to positions ``<= i`` only.

    With ``cache`` (a dict, initially empty) the keys/values of earlier calls are kept and the
    ``T`` new positions follow them: new position ``j`` attends to every cached position and
    to new positions ``<= j``. Feeding a sequence in pieces gives the same result as feeding
    it whole (the rollout's KV cache; the whole-sequence call is the reference). The cache
    holds buffers ``k``, ``v`` [N, heads, capacity, hd] of which the first ``n`` positions are
    valid; capacity doubles when full, so appending a frame copies that frame only (not the
    whole history, as a concatenation would).
    """

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    @staticmethod
    def _append(cache: dict, k: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Append k, v [N, heads, T, hd] to the cache; return all valid keys/values (views)."""
        past, t = cache.get("n", 0), k.shape[2]
        buf = cache.get("k")
        if buf is None or buf.shape[2] < past + t or buf.shape[0] != k.shape[0]:
            cap = max(2 * (past + t), 2 * (0 if buf is None else buf.shape[2]))
            shape = (*k.shape[:2], cap, k.shape[3])
            new_k = k.new_empty(shape)
            new_v = v.new_empty(shape)
            if past:
                new_k[:, :, :past] = buf[:, :, :past]
                new_v[:, :, :past] = cache["v"][:, :, :past]
            cache["k"], cache["v"] = new_k, new_v
        cache["k"][:, :, past : past + t] = k
        cache["v"][:, :, past : past + t] = v
        cache["n"] = past + t
        return cache["k"][:, :, : past + t], cache["v"][:, :, : past + t]

    def forward(self, x: torch.Tensor, cache: dict | None = None) -> torch.Tensor:
        n, t, d = x.shape
        q, k, v = self.qkv(x).view(n, t, 3, self.num_heads, d // self.num_heads).unbind(2)
        q, k, v = q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2)  # [N, heads, T, hd]
        if cache is not None:
            k, v = self._append(cache, k, v)
        if (
            t > 1
            and k.shape[2] <= SHORT_SEQUENCE
            and x.device.type == "cpu"  # a GPU rollout is launch-bound: one fused kernel
            and not torch.is_grad_enabled()  # training keeps the fused kernel and its backward
        ):
            out = short_causal_attention(q, k, v)
        else:
            out = causal_attention_reference(q, k, v)
        return self.proj(out.transpose(1, 2).reshape(n, t, d))


class CrossAttention(nn.Module):
    """Queries [N, Q, D] attend to keys/values [N, S, D] (no mask)."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, query: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        n, nq, d = query.shape
        h, hd = self.num_heads, d // self.num_heads
        q = self.q(query).view(n, nq, h, hd).transpose(1, 2)
        k, v = self.kv(context).view(n, context.shape[1], 2, h, hd).unbind(2)
        out = F.scaled_dot_product_attention(q, k.transpose(1, 2), v.transpose(1, 2))
        return self.proj(out.transpose(1, 2).reshape(n, nq, d))


class SceneBlock(nn.Module):
    """Causal temporal attention per cell + per-frame spatial mixing + MLP (pre-norm).

    Args:
        dim: D.
        num_heads: attention heads.
        mlp_ratio: MLP hidden width / D.

    Shapes: x [B, T, h, w, D] -> [B, T, h, w, D]. ``cache``: see :class:`CausalSelfAttention`.
    """

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float):
        super().__init__()
        self.norm_t = nn.LayerNorm(dim)
        self.attn = CausalSelfAttention(dim, num_heads)
        self.norm_s = nn.LayerNorm(dim)
        # Depth-wise 3x3 conv inside one frame: lets content move between neighbouring cells.
        self.spatial = nn.Conv2d(dim, dim, 3, padding=1, groups=dim)
        self.norm_m = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, max(1, int(dim * mlp_ratio)))

    def forward(self, x: torch.Tensor, cache: dict | None = None) -> torch.Tensor:
        b, t, h, w, d = x.shape
        # Temporal attention: one sequence of length T per (batch, cell).
        y = self.norm_t(x).permute(0, 2, 3, 1, 4).reshape(b * h * w, t, d)
        y = self.attn(y, cache).view(b, h, w, t, d).permute(0, 3, 1, 2, 4)
        x = x + y
        y = self.norm_s(x).reshape(b * t, h, w, d).permute(0, 3, 1, 2)
        x = x + self.spatial(y).permute(0, 2, 3, 1).reshape(b, t, h, w, d)
        return x + self.mlp(self.norm_m(x))


class EgoTemporalBlock(nn.Module):
    """Ego token reads its frame's scene (cross-attention), then causal attention over time.

    Shapes: ego [B, T, D], scene [B, T, h, w, D] -> [B, T, D]. ``cache``: see
    :class:`CausalSelfAttention`.
    """

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float):
        super().__init__()
        self.norm_q = nn.LayerNorm(dim)
        self.norm_kv = nn.LayerNorm(dim)
        self.cross = CrossAttention(dim, num_heads)
        self.norm_t = nn.LayerNorm(dim)
        self.attn = CausalSelfAttention(dim, num_heads)
        self.norm_m = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, max(1, int(dim * mlp_ratio)))

    def forward(
        self, ego: torch.Tensor, scene: torch.Tensor, cache: dict | None = None
    ) -> torch.Tensor:
        b, t, h, w, d = scene.shape
        q = self.norm_q(ego).reshape(b * t, 1, d)
        kv = self.norm_kv(scene).reshape(b * t, h * w, d)
        ego = ego + self.cross(q, kv).view(b, t, d)
        ego = ego + self.attn(self.norm_t(ego), cache)
        return ego + self.mlp(self.norm_m(ego))


class Downsample(nn.Module):
    """Per-frame stride-2 3x3 conv: [B, T, h, w, D] -> [B, T, ceil(h/2), ceil(w/2), D]."""

    def __init__(self, dim: int):
        super().__init__()
        self.conv = nn.Conv2d(dim, dim, 3, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, t, h, w, d = x.shape
        y = self.conv(x.reshape(b * t, h, w, d).permute(0, 3, 1, 2))
        return y.permute(0, 2, 3, 1).reshape(b, t, y.shape[-2], y.shape[-1], d)


class UpFuse(nn.Module):
    """Per-frame nearest up-sampling to the skip's size, concat with the skip, 3x3 conv fuse.

    Shapes: coarse [B, T, h', w', D], skip [B, T, h, w, D] -> [B, T, h, w, D].
    """

    def __init__(self, dim: int):
        super().__init__()
        self.fuse = nn.Conv2d(2 * dim, dim, 3, padding=1)
        self.norm = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, 2 * dim)

    def forward(self, coarse: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        b, t, h, w, d = skip.shape
        c = coarse.reshape(b * t, *coarse.shape[2:]).permute(0, 3, 1, 2)
        c = F.interpolate(c, size=(h, w), mode="nearest")
        s = skip.reshape(b * t, h, w, d).permute(0, 3, 1, 2)
        x = self.fuse(torch.cat([c, s], dim=1)).permute(0, 2, 3, 1).reshape(b, t, h, w, d)
        x = skip + x
        return x + self.mlp(self.norm(x))
