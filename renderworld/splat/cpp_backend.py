"""The ``cpp`` backend: tiled compositing in a C++/OpenMP CPU kernel with a hand-written backward.

Projection and binning are the pure-torch ones shared with the ``torch`` backend (so gradients
reach means, quats and scales through torch autograd); only the per-pixel compositing, where
almost all the time goes, runs in ``csrc/rasterize_cpu.cpp``. The kernel is compiled on first
use with ``torch.utils.cpp_extension.load_inline`` and cached under the package's cache root
(``$RENDERWORLD_CACHE_DIR``, default ``~/.cache/renderworld``)/``splat_ext/<hash>``, keyed by the
source, flags and torch version. If compilation fails :func:`cpp_available` returns False, a warning
says why once, and ``backend="auto"`` falls back to ``torch``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import warnings
from pathlib import Path

import torch

from renderworld.cache import cache_root
from renderworld.splat.binning import bin_gaussians
from renderworld.splat.projection import project_gaussians
from renderworld.splat.tiled import TILE_SIZE

__all__ = ["cpp_available", "load_extension", "rasterize_cpp"]

_SOURCE = Path(__file__).with_name("csrc") / "rasterize_cpu.cpp"
# -fno-trapping-math lets gcc vectorize the exp loop (float→int conversions); no code here
# relies on floating-point traps or errno.
_BASE_FLAGS = ["-O3", "-fopenmp", "-fno-trapping-math", "-fno-math-errno"]
_STATE: dict = {}
_LOG = logging.getLogger(__name__)


def _flags() -> list[str]:
    """Compiler flags: AVX2 + FMA when torch reports this CPU supports them (key of the cache)."""
    capability = torch.backends.cpu.get_cpu_capability()
    isa = ["-mavx2", "-mfma"] if capability in ("AVX2", "AVX512") else []
    return _BASE_FLAGS + isa


def _cache_root() -> Path:
    return cache_root() / "splat_ext"


def load_extension():
    """Compile (once, cached on disk) and import the CPU kernel.

    Returns:
        The extension module, or None when compilation failed (a warning says why).
    """
    if "module" in _STATE:
        return _STATE["module"]
    source = _SOURCE.read_text()
    flags = _flags()
    key = hashlib.sha256((source + str(flags) + torch.__version__).encode()).hexdigest()[:16]
    build_dir = _cache_root() / key
    try:
        from torch.utils.cpp_extension import load_inline

        build_dir.mkdir(parents=True, exist_ok=True)
        # ninja keys the build by the source's path: a cache reached through a symlink under
        # another name each time (a test session's temporary root) would recompile every time.
        build_dir = build_dir.resolve()
        if not any(build_dir.glob("*.so")):
            _LOG.info("compiling the C++ rasterizer kernel into %s (once, ~30-60 s)", build_dir)
        module = load_inline(
            name=f"renderworld_splat_{key}",
            cpp_sources=[source],
            functions=["splat_forward", "splat_backward"],
            extra_cflags=flags,
            extra_ldflags=["-fopenmp"],
            build_directory=str(build_dir),
            verbose=False,
        )
    except Exception as exc:  # any toolchain failure: fall back to pure torch
        warnings.warn(
            f"renderworld.splat: the C++ CPU kernel failed to compile ({type(exc).__name__}: "
            f"{str(exc)[:300]}); backend 'auto' uses the pure-torch tiled backend instead.",
            RuntimeWarning,
            stacklevel=2,
        )
        module = None
    _STATE["module"] = module
    return module


def cpp_available() -> bool:
    """Whether the CPU kernel compiles and loads here (compiles it on the first call)."""
    if os.environ.get("RENDERWORLD_DISABLE_CPP") == "1":
        return False
    return load_extension() is not None


class _Composite(torch.autograd.Function):
    """Kernel compositing; differentiable in means2d, conics, depths, opacities, features."""

    @staticmethod
    def forward(ctx, means2d, conics, depths, opacities, features, proj_static, bins, size):
        extents, pair_gauss = proj_static
        num_cams, width, height = size
        ext = load_extension()
        args = (
            means2d.contiguous(),
            conics.contiguous(),
            extents.contiguous(),
            depths.contiguous(),
            pair_gauss.contiguous(),
            opacities.contiguous(),
            features.contiguous(),
            bins.pair_ids.contiguous(),
            bins.tile_offsets.contiguous(),
        )
        geom = (bins.tiles_x, bins.tiles_y, bins.tile_size, width, height)
        out, t_final, last = ext.splat_forward(*args, num_cams, *geom)
        ctx.save_for_backward(*args, t_final, last)
        ctx.geom = geom
        return out

    @staticmethod
    def backward(ctx, grad_out):
        *args, t_final, last = ctx.saved_tensors
        means2d, pair_gauss, features, ids = args[0], args[4], args[6], args[7]
        rows = load_extension().splat_backward(
            *args, *ctx.geom, grad_out.contiguous(), t_final, last
        )
        num_g, dim = features.shape
        # Row layout: [u, v, conic a, b, c, opacity, depth, features...].
        g_pair = torch.zeros(means2d.shape[0], 6, dtype=rows.dtype, device=rows.device)
        g_pair.index_add_(0, ids, rows[:, [0, 1, 2, 3, 4, 6]])
        g_gauss = torch.zeros(num_g, 1 + dim, dtype=rows.dtype, device=rows.device)
        g_gauss.index_add_(0, pair_gauss[ids], torch.cat([rows[:, 5:6], rows[:, 7:]], dim=1))
        return (
            g_pair[:, 0:2],
            g_pair[:, 2:5],
            g_pair[:, 5],
            g_gauss[:, 0],
            g_gauss[:, 1:],
            None,
            None,
            None,
        )


def rasterize_cpp(
    means,
    quats,
    scales,
    opacities,
    features,
    viewmats,
    Ks,
    width,
    height,
    near,
    far,
    tile_size: int = TILE_SIZE,
):
    """Tiled rasterization with the C++ kernel (contract of :func:`renderworld.splat.rasterize`).

    Returns:
        ``(features [C, H, W, D], depth_sum [C, H, W], alpha [C, H, W])``.

    Raises:
        ValueError: if the kernel is not available (see :func:`cpp_available`).
    """
    if not cpp_available():
        raise ValueError("backend: 'cpp' requested but the C++ CPU kernel is not available")
    proj = project_gaussians(
        means, quats, scales, opacities, viewmats, Ks, width, height, near, far
    )
    num_cams = viewmats.shape[0]
    bins = bin_gaussians(proj, num_cams, width, height, tile_size)
    out = _Composite.apply(
        proj.means2d,
        proj.conics,
        proj.depths,
        opacities,
        features,
        (proj.extents, proj.gauss_ids),
        bins,
        (num_cams, width, height),
    )
    dim = features.shape[1]
    return out[..., :dim], out[..., dim], out[..., dim + 1]
