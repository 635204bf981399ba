"""The mixed-precision policy: networks under the caller's autocast, the rest in float32.

Under ``torch.autocast`` (CUDA bf16 / fp16, CPU bf16) matrix products run in the low precision
even when their inputs are float32, and bf16 keeps 8 bits of mantissa: a voxel centre 40 m away
lands ~0.2 m off, a 0.4 m voxel's projection moves by pixels, alpha compositing loses the
transmittance it tracks down to 1e-4 and nearest-code search picks other codes. So:

- convolutions, attention and MLPs (the networks) run under the caller's autocast;
- geometry (poses, projections, covariances), the rasterizer, vector quantization, the depth
  distributions and every loss run in float32 with autocast off; their inputs are cast there.

Helpers here mark those boundaries; nothing is done when no autocast is active (float64 inputs
stay float64). :func:`exact_float32` turns TensorFloat-32 off where labels are decided (CUDA
convolutions and matrix products use TF32, a 10-bit mantissa, by default on Ampere and later).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import Any, TypeVar

import torch

__all__ = [
    "LOW_PRECISION_DTYPES",
    "autocast_active",
    "autocast_off",
    "caller_autocast",
    "exact_float32",
    "float32_boundary",
    "to_float32",
]

#: Floating dtypes that autocast computes in and that the float32 boundaries widen.
LOW_PRECISION_DTYPES = (torch.bfloat16, torch.float16)

_F = TypeVar("_F", bound=Callable[..., Any])


def _device_types() -> tuple[str, ...]:
    return ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",)


def autocast_active(device_type: str) -> bool:
    """Whether an autocast context is enabled for ``device_type`` (``"cpu"`` / ``"cuda"``)."""
    return bool(torch.is_autocast_enabled(device_type))


def to_float32(x: Any) -> Any:
    """``x`` in float32 when it is a bf16 / fp16 tensor; anything else unchanged."""
    if isinstance(x, torch.Tensor) and x.dtype in LOW_PRECISION_DTYPES:
        return x.float()
    return x


@contextmanager
def autocast_off() -> Iterator[None]:
    """Disable autocast on every device type present (CPU, and CUDA when available)."""
    with ExitStack() as stack:
        for device_type in _device_types():
            stack.enter_context(torch.autocast(device_type, enabled=False))
        yield


def caller_autocast(device_type: str) -> torch.autocast:
    """A fresh autocast context equal to the one active now on ``device_type`` (or disabled).

    Capture it before entering :func:`autocast_off` to re-enable the caller's autocast around
    the network calls inside a float32 region.
    """
    return torch.autocast(
        device_type,
        dtype=torch.get_autocast_dtype(device_type),
        enabled=autocast_active(device_type),
    )


def float32_boundary(fn: _F) -> _F:
    """Decorator: run ``fn`` with autocast off and its bf16 / fp16 tensor arguments in float32.

    Only top-level positional and keyword tensors are cast (containers are left alone); the
    decorated function's own arithmetic then stays in float32 under any caller's autocast.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        args = tuple(to_float32(a) for a in args)
        kwargs = {k: to_float32(v) for k, v in kwargs.items()}
        with autocast_off():
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def _tf32_switches() -> list[tuple[Any, str, Any]]:
    """``(object, attribute, value that means exact float32)`` of this torch's TF32 switches."""
    cudnn = torch.backends.cudnn
    if hasattr(torch.backends, "fp32_precision"):
        # torch >= 2.9: the per-backend API (mixing it with the legacy allow_tf32 flags raises).
        return [
            (torch.backends.cuda.matmul, "fp32_precision", "ieee"),
            (cudnn.conv, "fp32_precision", "ieee"),
            (cudnn.rnn, "fp32_precision", "ieee"),
        ]
    return [(torch.backends.cuda.matmul, "allow_tf32", False), (cudnn, "allow_tf32", False)]


@contextmanager
def exact_float32() -> Iterator[None]:
    """TF32 off and deterministic cuDNN algorithms inside; every setting restored after.

    Use it where a readout decides labels (export, evaluation, threshold search), so the same
    checkpoint gives the same labels on CPU and CUDA up to float32 rounding (summation order).
    A no-op on a CPU-only machine apart from setting the flags.
    """
    cudnn = torch.backends.cudnn
    switches = _tf32_switches() + [(cudnn, "deterministic", True), (cudnn, "benchmark", False)]
    saved = [(obj, name, getattr(obj, name)) for obj, name, _ in switches]
    try:
        for obj, name, value in switches:
            setattr(obj, name, value)
        yield
    finally:
        for obj, name, value in reversed(saved):
            setattr(obj, name, value)
