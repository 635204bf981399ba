"""Fast inference-only encode/decode of a :class:`SceneTokenizer` (the planner's hot path).

Same weights and the same decisions as :meth:`SceneTokenizer.encode` / :meth:`SceneTokenizer.decode`
(the reference twin, used as the test oracle), computed differently where a CPU profile of the
Occ3D decoder (200x200x16, paper sizes) showed the time going:

* **Channels-last throughout.** oneDNN convolutions run on NHWC without re-ordering activations
  in and out of every call (about 1.5x per 3x3 conv on AVX-512); the class embedding's
  ``[B, X, Y, Z, E]`` output *is* the NHWC encoder input (no permute copy) and the codebook
  lookup's ``[B, h, w, C]`` is the NHWC decoder input. 1x1 convolutions (latent heads,
  attention projections, voxel heads) become ``F.linear`` on the channel axis.
* **No full-resolution intermediates that only feed a decision.** The decoder never builds the
  18-way log-probabilities ``[B, X, Y, Z, 18]`` (a ``log_softmax``, a broadcast add and a
  concatenation over 640k voxels x 17 per frame, ~1.5 s of the 8.8 s for six frames): the
  air-mask rule needs ``logsigmoid(a) >= log 0.5`` and the argmax of the non-air logits, which
  ``log_softmax`` and the added per-voxel constant do not change.
* **Nearest up-sampling fused into the following 3x3 conv.** ``conv3x3(up2(x))`` equals four
  2x2 convolutions of ``x`` (one per output phase, the 3 taps folded to 2), interleaved: 4/9
  of the multiply-adds and no 4x larger up-sampled copy.
* In-place SiLU and residual adds (no extra full-size allocations).

Floating-point sums run in another order (folded taps, linear vs 1x1 conv, NHWC kernels), so
results equal the reference's up to rounding: decoder scores within ~1e-4 relative, and a
discrete decision flips only where the reference's two best scores are that close (the tests
bound the flipped fraction). Outputs are float32 unless the caller runs under ``torch.autocast``.
"""

from __future__ import annotations

import math
import weakref

import torch
import torch.nn.functional as F
from torch import nn

from renderworld.constants import FREE_ID, NUM_OCC3D_CLASSES
from renderworld.tokenizer.am_vae import SceneTokenizer
from renderworld.tokenizer.backbone import AttnBlock, ResBlock, _Upsample
from renderworld.tokenizer.heads import _IDENTITY_ORDER, NON_AIR_IDS
from renderworld.tokenizer.tokens import Tokens

__all__ = ["FastSceneCodec", "cache_frames_per_pass"]

_CL = torch.channels_last
_LOG_HALF = math.log(0.5)


def _nhwc(x: torch.Tensor) -> torch.Tensor:
    """[N, C, H, W] (channels-last memory) -> the [N, H, W, C] view of the same storage."""
    return x.permute(0, 2, 3, 1)


class _Packed:
    """Weights in the layout the fast kernels want, re-derived when a weight changes.

    Keyed by the weight tensor (weak reference, so a replaced parameter is never confused with
    a new one at the same address) and checked against its in-place version counter and data
    pointer: ``load_state_dict`` or an optimizer step into the tokenizer invalidates the entry.
    Without it, oneDNN re-orders every 3x3 weight to channels-last on every call.
    """

    def __init__(self) -> None:
        self._entries: dict[tuple[int, str], tuple] = {}

    def get(self, weight: torch.Tensor, tag: str, make) -> torch.Tensor:
        key = (id(weight), tag)
        stamp = (weight._version, weight.data_ptr(), weight.dtype, weight.device)
        hit = self._entries.get(key)
        if hit is not None and hit[0]() is weight and hit[1] == stamp:
            return hit[2]
        packed = make(weight)
        drop = self._entries.pop  # the entry goes when the weight is freed
        self._entries[key] = (weakref.ref(weight, lambda _: drop(key, None)), stamp, packed)
        return packed


_PACKED = _Packed()


def _conv(x: torch.Tensor, conv: nn.Conv2d) -> torch.Tensor:
    w = _PACKED.get(conv.weight, "cl", lambda w: w.contiguous(memory_format=_CL))
    return F.conv2d(x, w, conv.bias, conv.stride, conv.padding).contiguous(memory_format=_CL)


def _gn(x: torch.Tensor, norm: nn.GroupNorm) -> torch.Tensor:
    y = F.group_norm(x, norm.num_groups, norm.weight, norm.bias, norm.eps)
    return y.contiguous(memory_format=_CL)


def _gn_silu(x: torch.Tensor, norm: nn.GroupNorm) -> torch.Tensor:
    return F.silu(_gn(x, norm), inplace=True)


def _linear_1x1(x_nhwc: torch.Tensor, conv: nn.Conv2d) -> torch.Tensor:
    """A 1x1 conv as a matmul over the channel axis: [..., C_in] -> [..., C_out]."""
    w = conv.weight
    return F.linear(x_nhwc, w.view(w.shape[0], w.shape[1]), conv.bias)


def _res_block(x: torch.Tensor, blk: ResBlock) -> torch.Tensor:
    h = _conv(_gn_silu(x, blk.norm1), blk.conv1)
    h = _conv(_gn_silu(h, blk.norm2), blk.conv2)
    skip = x if isinstance(blk.skip, nn.Identity) else _conv(x, blk.skip)
    return h.add_(skip)


def _attn_block(x: torch.Tensor, blk: AttnBlock) -> torch.Tensor:
    b, c, h, w = x.shape
    n = _nhwc(_gn(x, blk.norm)).reshape(b, h * w, c)
    q, k, v = _linear_1x1(n, blk.qkv).split(c, dim=-1)
    out = F.scaled_dot_product_attention(q[:, None], k[:, None], v[:, None])[:, 0]
    y = _linear_1x1(out, blk.proj).view(b, h, w, c).permute(0, 3, 1, 2)
    return y.add_(x)


def _folded_taps(w: torch.Tensor, axis: int) -> tuple[torch.Tensor, torch.Tensor]:
    """3 taps of a 3x3 kernel along ``axis`` seen through nearest 2x up-sampling -> 2 taps per
    output phase: phase 0 reads source offsets (-1, 0), phase 1 reads (0, +1)."""
    t0, t1, t2 = w.unbind(axis)
    return torch.stack([t0, t1 + t2], axis), torch.stack([t0 + t1, t2], axis)


def _phase_kernels(weight: torch.Tensor) -> torch.Tensor:
    """[C_out, C_in, 3, 3] -> [4 * C_out, C_in, 2, 2]: phase (a, b) in block 2a + b."""
    kernels = [wab for wa in _folded_taps(weight, 2) for wab in _folded_taps(wa, 3)]
    return torch.cat(kernels).contiguous(memory_format=_CL)


def _upsample_conv(x: torch.Tensor, up: _Upsample) -> torch.Tensor:
    """``conv3x3(nearest_up2(x))`` as one 2x2 convolution of ``x`` with 4x the output channels
    (one block per output phase), then interleaved (stride (2, 2), padding 1 only).

    With padding 1 a 2x2 conv gives (H+1) x (W+1) outputs, output (p, q) reading source rows
    p-1, p and columns q-1, q; phase (a, b) of the up-sampled output at (i, j) is output
    (i + a, j + b) of its block.
    """
    if tuple(up.stride) != (2, 2) or tuple(up.conv.padding) != (1, 1):
        y = F.interpolate(x, scale_factor=up.stride, mode="nearest")
        return _conv(y.contiguous(memory_format=_CL), up.conv)
    n, _, h, w = x.shape
    weight, bias = up.conv.weight, up.conv.bias
    c_out = weight.shape[0]
    kernel = _PACKED.get(weight, "up2", _phase_kernels)
    y = F.conv2d(x, kernel, None if bias is None else bias.repeat(4), padding=1)
    y = _nhwc(y.contiguous(memory_format=_CL))  # [N, H+1, W+1, 4 * C_out]
    out = torch.empty(n, h, 2, w, 2, c_out, dtype=y.dtype, device=y.device)
    for a in range(2):
        for b in range(2):
            blk = 2 * a + b
            out[:, :, a, :, b] = y[:, a : a + h, b : b + w, blk * c_out : (blk + 1) * c_out]
    return out.view(n, 2 * h, 2 * w, c_out).permute(0, 3, 1, 2)


def _run_blocks(x: torch.Tensor, blocks: nn.Sequential) -> torch.Tensor:
    for blk in blocks:
        if isinstance(blk, ResBlock):
            x = _res_block(x, blk)
        elif isinstance(blk, AttnBlock):
            x = _attn_block(x, blk)
        elif isinstance(blk, _Upsample):
            x = _upsample_conv(x, blk)
        elif isinstance(blk, nn.Conv2d):
            x = _conv(x, blk)
        else:  # pragma: no cover - the backbone only builds the four kinds above
            raise TypeError(f"blocks: unexpected module {type(blk).__name__}")
    return x


#: Bytes of full-resolution features a CPU pass may hold (well inside a 32 MiB L3 cache).
CPU_PASS_BYTES = 16 * 1024 * 1024


def cache_frames_per_pass(tokenizer: SceneTokenizer, budget: int = CPU_PASS_BYTES) -> int:
    """Frames per CPU pass whose full-resolution features ``[X, Y, C_0]`` float32 fit ``budget``
    bytes (at least 1): 1 at the Occ3D grid (200x200x64: 10 MB a frame), every frame of a
    planner call at the mini grid (50x50x32: 0.3 MB). Measured on a 2-core AVX2 EPYC (32 MiB
    L3): ten Occ3D encodes 6.4 s in one pass, 5.0 s a frame at a time; at the mini grid one
    pass per frame was 1.2-2.2x slower than one pass (docs/planner.md)."""
    x, y, _ = tokenizer.cfg.grid_shape
    per_frame = x * y * tokenizer.cfg.level_channels[0] * 4
    return max(1, budget // per_frame)


class FastSceneCodec:
    """Inference-only ``encode`` / ``decode`` of a :class:`SceneTokenizer`.

    Reads the tokenizer's modules on every call; weights it re-packs (channels-last, folded
    up-sampling kernels) are cached and re-derived when a weight changes, so loading a new
    state dict into the tokenizer is picked up. Never updates codebooks. Runs under
    ``torch.inference_mode()`` (no autograd).

    Args:
        tokenizer: the :class:`SceneTokenizer` (any variant).
        max_batch: most frames per pass through the encoder or decoder trunk (None: all at
            once). On a CPU, passes whose activations stay in the last-level cache are faster
            (:func:`cache_frames_per_pass`). A frame's result does not depend on the other
            frames of its pass beyond rounding (oneDNN picks its kernels by batch size).
    """

    def __init__(self, tokenizer: SceneTokenizer, max_batch: int | None = None):
        if not isinstance(tokenizer, SceneTokenizer):
            raise TypeError(f"tokenizer: expected SceneTokenizer, got {type(tokenizer).__name__}")
        if max_batch is not None and (type(max_batch) is not int or max_batch < 1):
            raise ValueError(f"max_batch: expected None or an int >= 1, got {max_batch!r}")
        self.tokenizer = tokenizer
        self.max_batch = max_batch

    def _passes(self, n: int) -> list[slice]:
        """Slices of a batch of ``n`` frames, one per pass (one empty slice when ``n`` is 0)."""
        step = n if self.max_batch is None else self.max_batch
        return [slice(i, i + step) for i in range(0, n, step)] or [slice(0, 0)]

    @torch.inference_mode()
    def encode(self, occ: torch.Tensor) -> Tokens:
        """Occupancy [B, X, Y, Z] uint8 Occ3D ids -> :class:`Tokens` [B, G, h, w] (nearest codes).

        Validated like :meth:`SceneTokenizer.encode`.
        """
        tok = self.tokenizer
        target = tok._check_occ(occ)
        parts = [self._encode_indices(target[p]) for p in self._passes(target.shape[0])]
        return tok._make_tokens([torch.cat(g) for g in zip(*parts)])

    def _encode_indices(self, target: torch.Tensor) -> list[torch.Tensor]:
        """Checked occupancy [B, X, Y, Z] int64 -> one [B, h, w] index map per codebook."""
        tok = self.tokenizer
        b, x, y, z = target.shape
        e = tok.embed.embed(target)  # [B, X, Y, Z, E]: channel z*E + e, as ClassEmbedding
        h = e.reshape(b, x, y, -1).permute(0, 3, 1, 2)  # channels-last view
        enc = tok.encoder
        h = _run_blocks(_conv(h, enc.conv_in), enc.blocks)
        f = _nhwc(_gn_silu(h, enc.norm_out))  # [B, h, w, D]
        idx = []
        for head, quant in zip(tok.latent_heads, tok.quantizers):
            zl = _linear_1x1(f, head).float()  # [B, h, w, C]
            cb = quant.codebook
            d = cb.pow(2).sum(1) - 2.0 * zl.reshape(-1, zl.shape[-1]) @ cb.t()
            idx.append(d.argmin(1).reshape(zl.shape[:3]))
        return idx

    @torch.inference_mode()
    def decode(self, tokens: Tokens) -> torch.Tensor:
        """Tokens [..., G, h, w] -> occupancy [..., X, Y, Z] uint8 (the variant's decision rule).

        Validated like :meth:`SceneTokenizer.decode`.
        """
        tok = self.tokenizer
        idx = tok._check_tokens(tokens)
        lead = idx.shape[:-3]
        flat = idx.reshape(-1, *idx.shape[-3:])
        occ = torch.cat([self._decode_indices(flat[p]) for p in self._passes(flat.shape[0])])
        return occ.reshape(*lead, *occ.shape[1:])

    def _decode_indices(self, flat: torch.Tensor) -> torch.Tensor:
        """Checked codes [B, G, h, w] -> occupancy [B, X, Y, Z] uint8."""
        tok, cfg = self.tokenizer, self.tokenizer.cfg
        b = flat.shape[0]
        q = [quant.codebook[flat[:, g]] for g, quant in enumerate(tok.quantizers)]  # [B,h,w,C]
        if cfg.variant == "am_vae":
            z = torch.cat(q, dim=0)  # both latents through the shared trunk, one batch
        elif cfg.variant == "separate":
            z = torch.cat(q, dim=-1)
        else:
            z = q[0]
        dec = tok.decoder
        h = _run_blocks(_conv(z.permute(0, 3, 1, 2), dec.conv_in), dec.blocks)
        feats = _nhwc(_gn_silu(h, dec.norm_out))  # [N, X, Y, D]
        if cfg.air_mask_head:
            fa, fn = (feats[:b], feats[b:]) if cfg.variant == "am_vae" else (feats, feats)
            occ = _air_mask_decision(
                _linear_1x1(fa, tok.air_head.conv), _linear_1x1(fn, tok.non_air_head.conv)
            )
        else:
            s = _linear_1x1(feats, tok.class_head.conv)
            occ = s.unflatten(-1, (-1, NUM_OCC3D_CLASSES)).argmax(-1).to(torch.uint8)
        return occ


def _air_mask_decision(air: torch.Tensor, non_air: torch.Tensor) -> torch.Tensor:
    """Eq. 6.13 on head outputs: air [N, X, Y, Z], non_air [N, X, Y, Z*17] -> uint8 [N, X, Y, Z].

    Free where ``logsigmoid(a) >= log 0.5`` (the reference's exact test), else the best
    non-air class by raw logits (``log_softmax`` plus a per-voxel constant keeps the argmax).
    """
    best = non_air.unflatten(-1, (-1, len(NON_AIR_IDS))).argmax(-1)
    if not _IDENTITY_ORDER:  # pragma: no cover - Occ3D ids put free last
        best = torch.tensor(NON_AIR_IDS, device=best.device)[best]
    free = F.logsigmoid(air.float()) >= _LOG_HALF
    return best.to(torch.uint8).masked_fill_(free, FREE_ID)
