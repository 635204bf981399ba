"""The mixed-precision helpers: float32 boundaries under autocast, TF32 switches restored."""

from __future__ import annotations

import pytest
import torch

from renderworld.precision import (
    autocast_off,
    caller_autocast,
    exact_float32,
    float32_boundary,
    to_float32,
)


@float32_boundary
def _product(a, b, scale=1.0):
    return (a @ b) * scale


def test_float32_boundary_casts_inputs_and_keeps_autocast_out():
    a, b = torch.randn(8, 8), torch.randn(8, 8)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert (a @ b).dtype == torch.bfloat16  # what autocast does to a float32 matmul
        out = _product(a.bfloat16(), b=b)
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, a.bfloat16().float() @ b)
    double = _product(a.double(), b.double())
    assert double.dtype == torch.float64  # only bf16 / fp16 are widened


def test_caller_autocast_restores_the_outer_state_inside_a_float32_region():
    x = torch.randn(4, 4)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        nets = caller_autocast("cpu")
        with autocast_off():
            assert (x @ x).dtype == torch.float32
            with nets:
                assert (x @ x).dtype == torch.bfloat16
    with caller_autocast("cpu"):
        assert (x @ x).dtype == torch.float32  # no outer autocast: nothing enabled


def test_to_float32_leaves_other_values_alone():
    assert to_float32(None) is None
    t = torch.zeros(2, dtype=torch.float16)
    assert to_float32(t).dtype == torch.float32
    i = torch.zeros(2, dtype=torch.long)
    assert to_float32(i) is i


def _flags():
    cudnn = torch.backends.cudnn
    if hasattr(torch.backends, "fp32_precision"):
        tf32 = (torch.backends.cuda.matmul.fp32_precision, cudnn.conv.fp32_precision)
    else:
        tf32 = (torch.backends.cuda.matmul.allow_tf32, cudnn.allow_tf32)
    return (*tf32, cudnn.deterministic, cudnn.benchmark)


def test_exact_float32_turns_tf32_off_and_restores_even_on_error():
    before = _flags()
    with exact_float32():
        inside = _flags()
    assert _flags() == before
    if hasattr(torch.backends, "fp32_precision"):
        assert inside[:2] == ("ieee", "ieee")
    else:
        assert inside[:2] == (False, False)
    assert inside[2:] == (True, False)
    with pytest.raises(RuntimeError, match="boom"), exact_float32():
        raise RuntimeError("boom")
    assert _flags() == before
