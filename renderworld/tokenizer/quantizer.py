"""Vector quantizer with straight-through gradients, EMA codebook and dead-code restarts.

Each latent cell ``z`` [C] is replaced by its nearest codebook entry ``e_k`` (Eq. 6.9,
Euclidean distance). Gradients pass straight through (``z + sg(e_k - z)``). The encoder is
pulled towards its codes by the commitment term ``beta * ||z - sg(e_k)||^2`` (Eq. 6.15); the
codebook follows the encoder either by exponential moving averages of the assigned vectors
(``ema=True``, no codebook gradient) or by the codebook loss ``||sg(z) - e_k||^2``.

Dead codes: every training step records, per code, the step it was last assigned. A code
unused for ``dead_code_steps`` steps (counted from its last use or restart) is moved onto a
random encoder output of the current batch (its EMA statistics reset to that vector), so a
codebook initialised far from the data or collapsed onto a few codes recovers. The very first
training batch also initialises the codebook from random encoder outputs (data-dependent init).

Under DistributedDataParallel with the default ``broadcast_buffers=True`` the EMA codebook (a
buffer) is broadcast from rank 0 at each forward, so ranks stay consistent.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from renderworld.precision import float32_boundary

__all__ = ["VectorQuantizer", "QuantizerOutput", "code_usage_stats"]


def code_usage_stats(indices: torch.Tensor, num_codes: int) -> dict[str, torch.Tensor]:
    """Usage and perplexity of one assignment.

    Args:
        indices: [...] int64 code indices in [0, num_codes).
        num_codes: K.

    Returns:
        ``{"usage": fraction of the K codes assigned at least once, "perplexity":
        exp(entropy of the assignment histogram)}`` as float32 scalars (perplexity is 1 when
        every cell uses one code and K when all codes are used equally).
    """
    counts = torch.bincount(indices.reshape(-1), minlength=num_codes).float()
    p = counts / counts.sum().clamp_min(1.0)
    entropy = -(p * torch.log(p.clamp_min(1e-12))).sum()
    return {"usage": (counts > 0).float().mean(), "perplexity": torch.exp(entropy)}


class QuantizerOutput:
    """Result of :meth:`VectorQuantizer.forward`.

    Attributes:
        quantized: [B, C, h, w] straight-through quantized latent.
        indices: [B, h, w] int64 code indices.
        loss: scalar, ``beta * commitment`` (+ codebook loss when not using EMA).
        stats: float scalars: ``usage`` (batch), ``perplexity`` (batch), ``window_usage``
            (fraction of codes used in the last ``usage_window`` training steps),
            ``restarted`` (codes restarted this step).
    """

    __slots__ = ("quantized", "indices", "loss", "stats")

    def __init__(self, quantized, indices, loss, stats) -> None:
        self.quantized, self.indices, self.loss, self.stats = quantized, indices, loss, stats


class VectorQuantizer(nn.Module):
    """Nearest-neighbour quantizer of [B, C, h, w] latents over a K x C codebook.

    Args:
        num_codes: K.
        dim: C.
        beta: Commitment weight.
        ema: EMA codebook updates (else a learnable codebook trained by the codebook loss).
        decay: EMA decay.
        dead_code_steps: Restart a code after this many training steps unused (0: never).
        usage_window: Steps over which ``window_usage`` counts a code as used.
        eps: Laplace smoothing of EMA cluster sizes.
    """

    def __init__(
        self,
        num_codes: int,
        dim: int,
        beta: float = 0.25,
        ema: bool = True,
        decay: float = 0.99,
        dead_code_steps: int = 100,
        usage_window: int = 100,
        eps: float = 1e-5,
    ) -> None:
        super().__init__()
        if num_codes < 1 or dim < 1:
            raise ValueError(f"num_codes, dim: expected positive ints, got {num_codes}, {dim}")
        self.num_codes, self.dim, self.beta = num_codes, dim, float(beta)
        self.ema, self.decay, self.eps = ema, decay, eps
        self.dead_code_steps, self.usage_window = dead_code_steps, usage_window
        init = torch.randn(num_codes, dim) / dim**0.5
        if ema:
            self.register_buffer("codebook", init)
            self.register_buffer("ema_size", torch.ones(num_codes))
            self.register_buffer("ema_sum", init.clone())
        else:
            self.codebook = nn.Parameter(init)
        # Training-step counter, step at which each code was last assigned / last restarted
        # (0 = never). Restarting a code does not count as using it.
        self.register_buffer("step", torch.zeros((), dtype=torch.int64))
        self.register_buffer("last_used", torch.zeros(num_codes, dtype=torch.int64))
        self.register_buffer("last_restart", torch.zeros(num_codes, dtype=torch.int64))
        self.register_buffer("initialized", torch.tensor(False))
        # Host-side copy of ``initialized`` once it is True: reading the buffer every step
        # would wait for the GPU (a host sync); a loaded state resets it.
        self._known_initialized = False

    # ------------------------------------------------------------------ public
    def lookup(self, indices: torch.Tensor) -> torch.Tensor:
        """Code vectors of ``indices`` [B, h, w] -> [B, C, h, w]."""
        return self.codebook[indices].permute(0, 3, 1, 2)

    def assign(self, z: torch.Tensor) -> torch.Tensor:
        """Nearest code per cell: z [B, C, h, w] -> indices [B, h, w] int64."""
        b, c, h, w = z.shape
        flat = z.detach().permute(0, 2, 3, 1).reshape(-1, c)
        cb = self.codebook.detach()
        # ||z||^2 - 2 z.e + ||e||^2; ||z||^2 does not change the argmin.
        d = cb.pow(2).sum(1)[None, :] - 2.0 * flat @ cb.t()
        return d.argmin(1).reshape(b, h, w)

    @float32_boundary  # nearest-code distances and EMA: bf16 matmuls pick other codes
    def forward(self, z: torch.Tensor) -> QuantizerOutput:
        """Quantize z [B, C, h, w]; in training mode also update the codebook and counters."""
        if z.dim() != 4 or z.shape[1] != self.dim:
            raise ValueError(f"z: expected [B, {self.dim}, h, w], got {tuple(z.shape)}")
        z = z.float()
        if self.training and not self._known_initialized:
            if not bool(self.initialized):
                self._init_from(z)
            self._known_initialized = True
        idx = self.assign(z)
        restarted = torch.zeros((), device=z.device)
        if self.training:
            with torch.no_grad():
                if self.ema:
                    self._ema_update(z, idx)
                restarted = self._count_and_restart(z, idx)
        q = self.lookup(idx)
        commit = F.mse_loss(z, q.detach())
        loss = self.beta * commit
        if not self.ema:
            loss = loss + F.mse_loss(q, z.detach())
        # Straight-through estimator, written so the value is exactly q (z - sg(z) == 0 in
        # floating point), which keeps decode(encode(x)) bit-identical to forward(x).
        quantized = q.detach() + (z - z.detach())
        stats = code_usage_stats(idx, self.num_codes)
        stats["window_usage"] = self.window_usage()
        stats["restarted"] = restarted.float()
        stats["commitment"] = commit.detach()
        return QuantizerOutput(quantized, idx, loss, stats)

    def window_usage(self) -> torch.Tensor:
        """Fraction of codes assigned within the last ``usage_window`` training steps."""
        recent = self.last_used > (self.step - self.usage_window)
        return (recent & (self.last_used > 0)).float().mean()

    # ------------------------------------------------------------------ internals
    @staticmethod
    def _sample_rows(z: torch.Tensor, n: int) -> torch.Tensor:
        flat = z.detach().permute(0, 2, 3, 1).reshape(-1, z.shape[1])
        if flat.shape[0] >= n:
            pick = torch.randperm(flat.shape[0], device=z.device)[:n]
        else:
            pick = torch.randint(flat.shape[0], (n,), device=z.device)
        return flat[pick]

    @torch.no_grad()
    def _init_from(self, z: torch.Tensor) -> None:
        rows = self._sample_rows(z, self.num_codes)
        self.codebook.data.copy_(rows)
        if self.ema:
            self.ema_sum.copy_(rows)
            self.ema_size.fill_(1.0)
        self.initialized.fill_(True)

    def _ema_update(self, z: torch.Tensor, idx: torch.Tensor) -> None:
        flat = z.detach().permute(0, 2, 3, 1).reshape(-1, self.dim)
        onehot = F.one_hot(idx.reshape(-1), self.num_codes).type_as(flat)  # [N, K]
        self.ema_size.mul_(self.decay).add_(onehot.sum(0), alpha=1 - self.decay)
        self.ema_sum.mul_(self.decay).add_(onehot.t() @ flat, alpha=1 - self.decay)
        n = self.ema_size.sum()
        size = (self.ema_size + self.eps) / (n + self.num_codes * self.eps) * n  # Laplace
        self.codebook.copy_(self.ema_sum / size[:, None])

    def _count_and_restart(self, z: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        used = torch.bincount(idx.reshape(-1), minlength=self.num_codes) > 0
        self.step.add_(1)
        self.last_used.masked_fill_(used, self.step)  # a tensor value: no host sync
        if self.dead_code_steps <= 0:
            return torch.zeros((), device=z.device)
        idle = self.step - torch.maximum(self.last_used, self.last_restart)
        dead = idle >= self.dead_code_steps
        n_dead = int(dead.sum())
        if n_dead:
            rows = self._sample_rows(z, n_dead)
            self.codebook.data[dead] = rows
            if self.ema:
                self.ema_sum[dead] = rows
                self.ema_size[dead] = 1.0
            self.last_restart[dead] = self.step
        return torch.tensor(float(n_dead), device=z.device)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        self._known_initialized = False  # re-read ``initialized`` from the loaded state
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
