"""Triton kernels (mcdenoise/ops/triton_kernels.py) vs the plain-PyTorch references, in Triton's
CPU interpreter.  Skipped where triton is not installed (`pip install -e '.[triton]'`).

These check the kernels' index arithmetic, masks and numerics only: nothing here compiles or
runs them on a GPU, and nothing times them.
"""

from __future__ import annotations

import os

# Must precede the first import of triton and of the kernel module: triton.jit reads it when the
# kernels are defined.
os.environ["TRITON_INTERPRET"] = "1"

import subprocess  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

pytest.importorskip("triton")

from mcdenoise.ops import gather_reference, importance_filter_reference, splat_reference  # noqa: E402
from mcdenoise.ops.triton_kernels import (  # noqa: E402
    gather_triton,
    importance_filter_triton,
    kernels_interpreted,
    splat_triton,
)

F64 = torch.float64
TOL = dict(rtol=1e-5, atol=1e-6)
# (H, W, K): odd sizes, borders everywhere at K = 5, and K larger than the image (15 > 9, 7 > 5).
SIZES = [(7, 9, 3), (7, 9, 5), (13, 5, 3), (13, 5, 5), (7, 9, 15), (13, 5, 7)]


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _assert_close_scaled(out: torch.Tensor, exact: torch.Tensor, scale: torch.Tensor, rtol: float = 1e-5, atol: float = 1e-6) -> None:
    """``|out - exact| <= atol + rtol * scale`` elementwise, ``exact`` the float64 reference and
    ``scale`` the same op on ``|values|`` (the sum of the terms' magnitudes): float32 sums of up to
    450 terms are off by a few eps of that sum where the terms cancel (measured: <= 4e-7 of it,
    the float32 reference itself is off as much), so an error relative to ``|exact|`` alone would
    flag correct results; an index or mask bug is off by O(1) of it."""
    assert out.dtype == torch.float32 and out.shape == exact.shape
    err = (out.double() - exact).abs()
    bound = atol + rtol * scale
    assert torch.isfinite(out).all()
    ratio = err / bound
    assert bool((ratio <= 1).all()), f"error {float(ratio.max()):.3g} x the bound at flat index {int(ratio.argmax())}"


def _noncontig(x: torch.Tensor) -> torch.Tensor:
    y = x.transpose(-1, -2).contiguous().transpose(-1, -2)
    assert not y.is_contiguous() and torch.equal(y, x)
    return y


def test_interpreter_runs_on_cpu_tensors() -> None:
    """Catches a test run that silently is not in the interpreter (TRITON_INTERPRET set too late):
    the kernels must be interpreted functions and take and return CPU tensors."""
    assert kernels_interpreted()
    x = torch.randn(1, 1, 3, 3, generator=_gen())
    w = torch.zeros(1, 9, 3, 3)
    w[:, 4] = 1
    out = gather_triton(x, w)
    assert out.device.type == "cpu"
    torch.testing.assert_close(out, x, rtol=0, atol=0)


def test_import_ops_does_not_need_triton() -> None:
    """Catches an eager `import triton` in mcdenoise.ops (the package must import without it)."""
    code = "import sys, mcdenoise.ops; assert 'triton' not in sys.modules, 'triton imported'"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("TRITON_INTERPRET", None)
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)


# ---------------------------------------------------------------- gather


@pytest.mark.parametrize("h,w,k", SIZES)
def test_gather_matches_reference(h: int, w: int, k: int) -> None:
    """Catches a flipped or transposed tap offset, wrong zero padding at the border or for K larger
    than the image, and a wrong batch / channel stride (B = 2, C = 3)."""
    g = _gen(k * 100 + h)
    x = torch.randn(2, 3, h, w, generator=g)
    wt = torch.softmax(torch.randn(2, k * k, h, w, generator=g), dim=1)
    xd, wd = x.to(F64), wt.to(F64)
    _assert_close_scaled(gather_triton(x, wt), gather_reference(xd, wd), gather_reference(xd.abs(), wd))


def test_gather_signed_weights_noncontiguous_float64() -> None:
    """Catches a kernel that reads raw strides of non-contiguous inputs, and float64 input summed in
    float32 (checked at float64 tolerance); signed, unnormalised weights, C = 20 > one channel block."""
    g = _gen(1)
    x = _noncontig(torch.randn(2, 20, 7, 9, generator=g, dtype=torch.float64))
    wt = _noncontig(torch.randn(2, 25, 7, 9, generator=g, dtype=torch.float64))
    out = gather_triton(x, wt)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, gather_reference(x, wt), rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------- splat


@pytest.mark.parametrize("h,w,k", SIZES)
def test_splat_matches_reference(h: int, w: int, k: int) -> None:
    """Catches gather-form splat reading the source at p + d instead of p - d, dropped or
    double-counted samples (S = 2), contributions leaking in from outside the image, and a wrong
    weight sum."""
    g = _gen(k * 100 + h + 1)
    v = torch.randn(2, 2, 3, h, w, generator=g)
    wt = torch.rand(2, 2, k * k, h, w, generator=g)
    num, wsum = splat_triton(v, wt)
    vd, wd = v.to(F64), wt.to(F64)
    rnum, rwsum = splat_reference(vd, wd)
    _assert_close_scaled(num, rnum, splat_reference(vd.abs(), wd)[0])
    _assert_close_scaled(wsum, rwsum, rwsum)


def test_splat_impulse_lays_out_kernel() -> None:
    """Catches a splat that is secretly a gather (flipped kernel): one sample at (2, 3) with an
    asymmetric kernel must put tap i * K + j at (2 + i - 1, 3 + j - 1)."""
    k, h, w = 3, 5, 7
    v = torch.zeros(1, 1, 1, h, w)
    v[0, 0, 0, 2, 3] = 1.0
    wt = torch.zeros(1, 1, k * k, h, w)
    wt[0, 0, :, 2, 3] = torch.arange(1.0, 10.0)
    num, wsum = splat_triton(v, wt)
    expect = torch.zeros(h, w)
    expect[1:4, 2:5] = torch.arange(1.0, 10.0).reshape(3, 3)
    torch.testing.assert_close(num[0, 0], expect, rtol=0, atol=0)
    torch.testing.assert_close(wsum[0, 0], expect, rtol=0, atol=0)


def test_splat_many_channels_noncontiguous() -> None:
    """Catches a weight sum written by the wrong (or no) channel block when C = 20 spans two
    blocks, and non-contiguous inputs read with contiguous strides."""
    g = _gen(2)
    v = _noncontig(torch.randn(2, 3, 20, 7, 9, generator=g))
    wt = _noncontig(torch.rand(2, 3, 9, 7, 9, generator=g))
    num, wsum = splat_triton(v, wt)
    vd, wd = v.to(F64), wt.to(F64)
    rnum, rwsum = splat_reference(vd, wd)
    _assert_close_scaled(num, rnum, splat_reference(vd.abs(), wd)[0])
    _assert_close_scaled(wsum, rwsum, rwsum)


# ---------------------------------------------------------------- importance filter


@pytest.mark.parametrize("h,w,k", SIZES)
def test_importance_matches_reference(h: int, w: int, k: int) -> None:
    """Catches padding pixels taking part in the window softmax (windows must be clipped), a wrong
    window offset, and the max / exp passes disagreeing about which taps are inside."""
    g = _gen(k * 100 + h + 2)
    x = torch.randn(2, 3, h, w, generator=g)
    imp = 2 * torch.randn(2, 1, h, w, generator=g)
    xd, impd = x.to(F64), imp.to(F64)
    exact, scale = importance_filter_reference(xd, impd, k), importance_filter_reference(xd.abs(), impd, k)
    _assert_close_scaled(importance_filter_triton(x, imp, k), exact, scale)
    # The float32 reference itself, at the usual tolerance (importance weights are positive and
    # sum to one, so there is little cancellation here).
    torch.testing.assert_close(importance_filter_triton(x, imp, k), importance_filter_reference(x, imp, k), **TOL)


@pytest.mark.parametrize("k", [3, 5, 15])
def test_importance_huge_range_is_finite_and_exact(k: int) -> None:
    """Catches overflow / underflow to inf or 0/0 (NaN) from exp(I) without a shift, or with one
    global shift (a window 300 below the image maximum underflows to 0/0): importances spanning
    > 600 with bright and dark extremes at the corners and in the interior."""
    g = _gen(k)
    x = torch.randn(2, 3, 13, 5, generator=g)
    imp = 60 * torch.randn(2, 1, 13, 5, generator=g)
    imp[0, 0, 0, 0], imp[0, 0, 6, 2], imp[1, 0, 12, 4] = 300.0, -300.0, 250.0
    imp[1, 0, :4] -= 200.0
    assert float(imp.max() - imp.min()) > 100
    out = importance_filter_triton(x, imp, k)
    assert torch.isfinite(out).all()
    xd, impd = x.to(F64), imp.to(F64)
    _assert_close_scaled(out, importance_filter_reference(xd, impd, k), importance_filter_reference(xd.abs(), impd, k))
    torch.testing.assert_close(out, importance_filter_reference(x, imp, k), **TOL)


def test_importance_constant_is_clipped_box_mean() -> None:
    """Catches border windows divided by k*k instead of their in-image count: constant importance
    gives avg_pool2d(count_include_pad=False); float64 checks the float64 accumulation path."""
    x = torch.randn(2, 3, 7, 9, generator=_gen(3), dtype=torch.float64)
    imp = torch.full((2, 1, 7, 9), 5.0, dtype=torch.float64)
    expect = F.avg_pool2d(x, 5, stride=1, padding=2, count_include_pad=False)
    torch.testing.assert_close(importance_filter_triton(x, imp, 5), expect, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------- input checks


def test_bad_inputs_raise_clear_errors() -> None:
    """Catches kernels launched on mismatched shapes (out-of-bounds reads) instead of a ValueError
    naming the expected shape; and a silent no-gradient result for inputs that need one."""
    x = torch.randn(2, 3, 7, 9)
    with pytest.raises(ValueError, match="K\\*K"):
        gather_triton(x, torch.randn(2, 8, 7, 9))
    with pytest.raises(ValueError, match="weights must have shape"):
        gather_triton(x, torch.randn(1, 9, 7, 9))
    with pytest.raises(ValueError, match="values must have shape"):
        splat_triton(x, torch.randn(2, 1, 9, 7, 9))
    with pytest.raises(ValueError, match="weights must have shape"):
        splat_triton(torch.randn(2, 1, 3, 7, 9), torch.randn(2, 2, 9, 7, 9))
    with pytest.raises(ValueError, match="size must be a positive odd int"):
        importance_filter_triton(x, torch.randn(2, 1, 7, 9), 4)
    with pytest.raises(ValueError, match="importance must have shape"):
        importance_filter_triton(x, torch.randn(2, 2, 7, 9), 3)
    with pytest.raises(ValueError, match="share device and dtype"):
        gather_triton(x, torch.randn(2, 9, 7, 9, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="forward-only"):
        gather_triton(x.requires_grad_(), torch.randn(2, 9, 7, 9))
