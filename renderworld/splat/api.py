"""Public entry point: validate inputs, pick a backend, normalise depth."""

from __future__ import annotations

import importlib.util

import torch

from renderworld.precision import autocast_active, autocast_off, to_float32
from renderworld.splat.cpp_backend import cpp_available, rasterize_cpp
from renderworld.splat.gsplat_backend import rasterize_gsplat
from renderworld.splat.reference import rasterize_reference
from renderworld.splat.result import DEPTH_EPS, RenderResult
from renderworld.splat.tiled import rasterize_tiled

__all__ = ["RenderResult", "rasterize", "BACKENDS", "available_backends"]

#: Backend names accepted by :func:`rasterize` (plus ``"auto"``).
BACKENDS = ("reference", "torch", "cpp", "gsplat")


def _gsplat_importable() -> bool:
    return importlib.util.find_spec("gsplat") is not None


def available_backends(device: torch.device | str = "cpu") -> list[str]:
    """Backends usable for tensors on ``device`` in this environment."""
    device = torch.device(device)
    names = ["reference", "torch"]
    if device.type == "cpu":
        if cpp_available():
            names.append("cpp")
    if device.type == "cuda" and _gsplat_importable():
        names.append("gsplat")
    return names


def _check_tensor(name: str, t, shape: tuple, ndim: int) -> None:
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if not t.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {t.dtype}")
    bad = t.dim() != ndim or any(s is not None and s != g for s, g in zip(shape, t.shape))
    if bad:
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(t.shape)}")


def _validate(means, quats, scales, opacities, features, viewmats, Ks, width, height, near, far):
    _check_tensor("means", means, (None, 3), 2)
    n = means.shape[0]
    _check_tensor("quats", quats, (n, 4), 2)
    _check_tensor("scales", scales, (n, 3), 2)
    _check_tensor("opacities", opacities, (n,), 1)
    _check_tensor("features", features, (n, None), 2)
    _check_tensor("viewmats", viewmats, (None, 4, 4), 3)
    c = viewmats.shape[0]
    _check_tensor("Ks", Ks, (c, 3, 3), 3)
    if c == 0:
        raise ValueError("viewmats: expected at least one camera, got C = 0")
    if features.shape[1] == 0:
        raise ValueError("features: expected at least one channel, got D = 0")
    named = dict(quats=quats, scales=scales, opacities=opacities, features=features)
    named.update(viewmats=viewmats, Ks=Ks)
    for name, t in named.items():
        if t.dtype != means.dtype:
            raise TypeError(f"{name}: expected dtype {means.dtype} (that of means), got {t.dtype}")
        if t.device != means.device:
            raise ValueError(
                f"{name}: expected device {means.device} (that of means), got {t.device}"
            )
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValueError(f"{name}: expected a positive int, got {v!r}")
    if not (0 < near < far):
        raise ValueError(f"near/far: expected 0 < near < far, got near={near}, far={far}")
    if bool((Ks[:, 0, 1] != 0).any()):
        raise ValueError("Ks: expected zero skew (K[0, 1] == 0); skewed intrinsics not supported")


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    backend: str = "auto",
) -> RenderResult:
    """Render Gaussians' features, expected depth and alpha into C pinhole cameras.

    Differentiable with respect to means, quats, scales, opacities and features. Gaussians are
    evaluated at pixel centres (i + 0.5, j + 0.5) with the EWA 2D covariance plus a 0.3 px²
    low-pass; alpha = min(0.99, opacity·exp(-½ dᵀΣ'⁻¹d)), pairs with alpha < 1/255 skipped,
    front to back by camera z, a pixel stops before transmittance would reach 1e-4. Gaussian
    activations (bounded scales, sigmoid opacities, normalised quaternions) are the caller's
    job; raw extreme values still render finitely. Gaussians with a non-finite projection (NaN
    or infinite inputs) are culled like those outside the frustum.

    Backends agree to float rounding (``torch`` and ``cpp`` match ``reference`` to 1e-5 in
    float64): the CPU backends bound each Gaussian by the exact box where its alpha reaches
    1/255, so tiling never changes the image. ``cpp`` accumulates transmittance as a product,
    ``reference`` and ``torch`` in log space; ``gsplat`` differs slightly (3σ bound, see
    :mod:`renderworld.splat.gsplat_backend`).

    Args:
        means: [N, 3] centres, world frame (metres).
        quats: [N, 4] rotations (w, x, y, z), any non-negative norm (normalised with an epsilon;
            a zero quaternion means identity).
        scales: [N, 3] standard deviations along the Gaussian's local axes (metres).
        opacities: [N] opacities in [0, 1].
        features: [N, D] any number of channels (e.g. 17 semantic logits or probabilities).
        viewmats: [C, 4, 4] world→camera transforms (camera: z forward, x right, y down).
        Ks: [C, 3, 3] intrinsics in pixels of the rendered image (zero skew).
        width: image width W (pixels).
        height: image height H (pixels).
        near: Gaussians whose centre has camera z < near are culled (metres).
        far: Gaussians whose centre has camera z > far are culled (metres).
        backend: ``"auto"`` (gsplat for CUDA tensors when installed, else ``cpp`` on CPU when
            its kernel compiles, else ``torch``), ``"reference"`` (dense oracle, small inputs),
            ``"torch"`` (tiled pure torch), ``"cpp"`` (tiled C++/OpenMP CPU kernel) or
            ``"gsplat"`` (CUDA).

    Mixed precision: under ``torch.autocast`` bf16 / fp16 inputs are cast to float32 and the
    rasterizer runs in float32 (autocast off inside); outside autocast every input must share
    ``means``' dtype.

    Returns:
        :class:`RenderResult` (features [C, H, W, D], depth [C, H, W], alpha [C, H, W]) in the
        dtype (float32 under autocast) and on the device of the inputs.

    Raises:
        ValueError: wrong shapes, devices, sizes, near/far, or an unknown/unusable backend.
        TypeError: non-tensor or non-floating inputs, or mixed dtypes.
    """
    if isinstance(means, torch.Tensor) and autocast_active(means.device.type):
        # Under autocast the inputs arrive in mixed dtypes (network outputs in bf16 / fp16);
        # the rasterizer runs in float32: bf16's 8-bit mantissa cannot carry transmittance
        # down to 1e-4 nor the EWA covariance inverses.
        means, quats, scales, opacities, features, viewmats, Ks = (
            to_float32(t) for t in (means, quats, scales, opacities, features, viewmats, Ks)
        )
    _validate(means, quats, scales, opacities, features, viewmats, Ks, width, height, near, far)
    backend = _choose_backend(backend, means.device)
    args = (means, quats, scales, opacities, features, viewmats, Ks, width, height, near, far)
    # Autocast off: projection, 2-D covariance inverses and compositing stay in the inputs'
    # dtype (float32 under autocast) instead of bf16 matrix products.
    with autocast_off():
        if backend == "gsplat":
            return rasterize_gsplat(*args)
        if backend == "reference":
            feats, depth_sum, alpha = rasterize_reference(*args)
        elif backend == "torch":
            feats, depth_sum, alpha = rasterize_tiled(*args)
        else:
            feats, depth_sum, alpha = rasterize_cpp(*args)
        depth = depth_sum / alpha.clamp_min(DEPTH_EPS)
    return RenderResult(feats, depth, alpha)


def _choose_backend(backend: str, device: torch.device) -> str:
    """The backend ``rasterize`` runs for ``backend`` ("auto" resolved) on ``device``.

    Raises:
        ValueError: an unknown backend, or one that cannot run on ``device`` / is not installed.
    """
    if backend not in BACKENDS + ("auto",):
        raise ValueError(f"backend: expected one of {('auto',) + BACKENDS}, got {backend!r}")
    if backend == "auto":
        names = available_backends(device)
        return "gsplat" if "gsplat" in names else "cpp" if "cpp" in names else "torch"
    if backend == "cpp" and device.type != "cpu":
        raise ValueError(f"backend: 'cpp' needs CPU tensors, got device {device}")
    if backend == "gsplat":
        if device.type != "cuda":
            raise ValueError(f"backend: 'gsplat' needs CUDA tensors, got device {device}")
        if not _gsplat_importable():
            raise ValueError("backend: 'gsplat' requested but gsplat is not installed")
    return backend
