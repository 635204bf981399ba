"""Public API: validation messages, backend dispatch, the C++ kernel's fallback."""

import warnings
from pathlib import Path

import pytest
import torch

import renderworld.splat.cpp_backend as cpp_backend
from renderworld.splat import RenderResult, available_backends, rasterize
from tests.splat.scenes import HEIGHT, WIDTH, look_at_cameras, random_scene


def _args(n=4, dtype=torch.float64):
    viewmats, Ks = look_at_cameras(2, dtype)
    return random_scene(n, seed=0, dtype=dtype) + [viewmats, Ks, WIDTH, HEIGHT]


@pytest.mark.parametrize(
    "index, value, error, match",
    [
        (0, torch.zeros(4, 2, dtype=torch.float64), ValueError, r"means: expected shape \[\*, 3\]"),
        (1, torch.zeros(3, 4, dtype=torch.float64), ValueError, r"quats: expected shape \[4, 4\]"),
        (2, torch.zeros(4, 3, 1, dtype=torch.float64), ValueError, r"scales: expected shape"),
        (3, torch.zeros(4, 1, dtype=torch.float64), ValueError, r"opacities: expected shape \[4\]"),
        (
            4,
            torch.zeros(5, 3, dtype=torch.float64),
            ValueError,
            r"features: expected shape \[4, \*\]",
        ),
        (
            4,
            torch.zeros(4, 0, dtype=torch.float64),
            ValueError,
            r"features: .*at least one channel",
        ),
        (5, torch.eye(3, dtype=torch.float64)[None], ValueError, r"viewmats: expected shape"),
        (6, torch.eye(3, dtype=torch.float64)[None], ValueError, r"Ks: expected shape \[2, 3, 3\]"),
        (3, torch.ones(4, dtype=torch.long), TypeError, r"opacities: expected a floating-point"),
        (
            4,
            torch.ones(4, 3, dtype=torch.float32),
            TypeError,
            r"features: expected dtype torch.float64",
        ),
        (0, [[0.0, 0.0, 1.0]], TypeError, r"means: expected a torch.Tensor, got list"),
        (7, 0, ValueError, r"width: expected a positive int, got 0"),
        (8, 2.5, ValueError, r"height: expected a positive int, got 2.5"),
    ],
)
def test_validation_errors_name_the_argument(index, value, error, match):
    args = _args()
    args[index] = value
    with pytest.raises(error, match=match):
        rasterize(*args)


def test_near_far_skew_and_backend_errors():
    args = _args()
    with pytest.raises(ValueError, match=r"near/far: expected 0 < near < far, got near=0"):
        rasterize(*args, near=0.0)
    with pytest.raises(ValueError, match=r"near/far: expected 0 < near < far"):
        rasterize(*args, near=5.0, far=1.0)
    with pytest.raises(ValueError, match=r"backend: expected one of .*got 'cuda'"):
        rasterize(*args, backend="cuda")
    with pytest.raises(ValueError, match=r"backend: 'gsplat' needs CUDA tensors"):
        rasterize(*args, backend="gsplat")
    skewed = args[6].clone()
    skewed[0, 0, 1] = 0.5
    args[6] = skewed
    with pytest.raises(ValueError, match=r"Ks: expected zero skew"):
        rasterize(*args)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.gpu
def test_device_mismatch_is_reported():
    args = _args()
    args[4] = args[4].cuda()
    with pytest.raises(ValueError, match=r"features: expected device cpu"):
        rasterize(*args)


def test_result_shapes_dtypes_and_named_fields():
    for dtype in (torch.float32, torch.float64):
        r = rasterize(*_args(dtype=dtype), backend="torch")
        assert isinstance(r, RenderResult)
        assert r.features.shape == (2, HEIGHT, WIDTH, 3)
        assert r.depth.shape == r.alpha.shape == (2, HEIGHT, WIDTH)
        assert r.features.dtype == r.depth.dtype == r.alpha.dtype == dtype


def test_auto_matches_the_best_available_cpu_backend():
    args = _args(n=30)
    names = available_backends("cpu")
    expected = "cpp" if "cpp" in names else "torch"
    auto = rasterize(*args, backend="auto")
    explicit = rasterize(*args, backend=expected)
    for a, b in zip(auto, explicit):
        assert torch.equal(a, b)


def test_cpp_compile_failure_warns_and_auto_falls_back_to_torch(monkeypatch):
    import torch.utils.cpp_extension as ext

    def broken(*_args, **_kwargs):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(ext, "load_inline", broken)
    monkeypatch.setattr(cpp_backend, "_STATE", {})
    with pytest.warns(RuntimeWarning, match=r"C\+\+ CPU kernel failed to compile .*no compiler"):
        assert not cpp_backend.cpp_available()
    assert "cpp" not in available_backends("cpu")
    args = _args(n=30)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # warned once, not on every call
        auto = rasterize(*args)
    ref = rasterize(*args, backend="torch")
    for a, b in zip(auto, ref):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match=r"backend: 'cpp' requested but the C\+\+ CPU kernel"):
        rasterize(*args, backend="cpp")


def test_the_kernel_builds_in_the_real_cache_path_behind_a_symlink(monkeypatch, tmp_path):
    """ninja keys a build by its source path: a cache root reached through a symlink (a test
    session's temporary root) must build where the link points, or every session recompiles."""
    import torch.utils.cpp_extension as ext

    real = tmp_path / "real"
    real.mkdir()
    (tmp_path / "link").symlink_to(real, target_is_directory=True)
    monkeypatch.setenv("RENDERWORLD_CACHE_DIR", str(tmp_path / "link"))
    seen = {}

    def fake(**kwargs):
        seen["dir"] = kwargs["build_directory"]
        return object()

    monkeypatch.setattr(ext, "load_inline", fake)
    monkeypatch.setattr(cpp_backend, "_STATE", {})
    assert cpp_backend.load_extension() is not None
    assert Path(seen["dir"]).parent == real.resolve() / "splat_ext"


def test_disable_env_var_turns_the_kernel_off(monkeypatch):
    monkeypatch.setenv("RENDERWORLD_DISABLE_CPP", "1")
    assert "cpp" not in available_backends("cpu")
