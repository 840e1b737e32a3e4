"""Importance-map kernels (WSKP Eq. 2-5): ratio-of-box-sums fast path vs unfold + softmax reference."""

from __future__ import annotations

import pytest
import torch

from conftest import DEVICES
import torch.nn.functional as F

from mcdenoise.ops import (
    box_sum,
    fused_importance_filter,
    importance_filter,
    importance_filter_reference,
    importance_kernel_reference,
)

F64 = torch.float64


def _clipped_box_mean(x: torch.Tensor, size: int) -> torch.Tensor:
    """Mean over the in-image part of each size x size window (independent of box_sum)."""
    return F.avg_pool2d(x, size, stride=1, padding=size // 2, count_include_pad=False)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("size", [1, 3, 5, 13])
@pytest.mark.parametrize("c", [1, 3])
def test_importance_fast_matches_reference(device: str, size: int, c: int) -> None:
    g = torch.Generator().manual_seed(size * 10 + c)
    x = torch.randn(2, c, 7, 9, generator=g, dtype=F64).to(device)
    imp = (3 * torch.randn(2, 1, 7, 9, generator=g, dtype=F64)).to(device)
    ref = importance_filter_reference(x, imp, size)
    fast = importance_filter(x.transpose(-1, -2).contiguous().transpose(-1, -2), imp, size, impl="fast")
    torch.testing.assert_close(fast, ref, rtol=1e-11, atol=1e-12)


def _range_case(flip: bool) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 3, 10, 12, generator=g, dtype=F64)
    imp = torch.rand(1, 1, 10, 12, generator=g, dtype=F64) * 40
    imp[..., :5, :] -= 400
    return (x.flip(-2), imp.flip(-2)) if flip else (x, imp)


@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_importance_wide_range(flip: bool, dtype: torch.dtype) -> None:
    """Importances spanning 400 in one image, dim rows first or last. Catches an image-wide shift
    (float32 exp(I - max) underflows to 0/0 in the dim windows) and running-sum differences (with
    the bright rows first, the dim rows' sums cancel to 0/0: NaN in float64 and float32, issue 8
    bug 3)."""
    x, imp = _range_case(flip)
    ref = importance_filter_reference(x, imp, 5)
    fast = importance_filter(x.to(dtype), imp.to(dtype), 5, impl="fast")
    assert fast.dtype == dtype and torch.isfinite(fast).all()
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == F64 else dict(rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fast.double(), ref, **tol)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_importance_spike_above_its_row(dtype: torch.dtype) -> None:
    """One importance 40 above the rest of its row (32 x 32, k = 13): the running sums after it
    differ by exp(-40) relative, below float64 resolution, so later windows became 0/0 = NaN
    (issue 8 bug 3). The per-window shift keeps every denominator >= 1."""
    g = torch.Generator().manual_seed(2)
    x = torch.rand(1, 3, 32, 32, generator=g, dtype=F64)
    imp = torch.rand(1, 1, 32, 32, generator=g, dtype=F64)
    imp[0, 0, 5, 3] = 40.0
    ref = importance_filter_reference(x, imp, 13)
    fast = importance_filter(x.to(dtype), imp.to(dtype), 13, impl="fast")
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == F64 else dict(rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(fast.double(), ref, **tol)


def test_importance_spread_of_30_is_exact() -> None:
    """Importances spread over 30 with the high ones first: running-sum differences lost ~1e-4
    (issue 8 bug 3); direct sums stay at float64 rounding."""
    g = torch.Generator().manual_seed(6)
    x = torch.rand(2, 3, 24, 24, generator=g, dtype=F64)
    imp = torch.rand(2, 1, 24, 24, generator=g, dtype=F64)
    imp[..., :, :8] += 30.0
    ref = importance_filter_reference(x, imp, 13)
    torch.testing.assert_close(importance_filter(x, imp, 13, impl="fast"), ref, rtol=1e-12, atol=1e-12)


def test_importance_float32_accumulates_in_float32() -> None:
    """Catches a return to float64 accumulation for float32 inputs (half of WSKP's CPU time and
    32-64x slower on consumer GPUs): no float64 tensor may be created. Half precision inputs are
    accumulated in float32 and returned in their own dtype."""
    from torch.utils._python_dispatch import TorchDispatchMode

    seen: set[torch.dtype] = set()

    class Dtypes(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
            out = func(*args, **(kwargs or {}))
            for t in out if isinstance(out, (tuple, list)) else (out,):
                if isinstance(t, torch.Tensor):
                    seen.add(t.dtype)
            return out

    x, imp = (t.float() for t in _range_case(True))
    with Dtypes():
        importance_filter(x, imp, 7, impl="fast")
    assert torch.float64 not in seen, seen
    out = importance_filter(x.bfloat16(), imp.bfloat16(), 7, impl="fast")
    ref = importance_filter_reference(x.bfloat16().double(), imp.bfloat16().double(), 7)
    assert out.dtype == torch.bfloat16
    torch.testing.assert_close(out.double(), ref, rtol=1e-2, atol=1e-2)


@pytest.mark.parametrize("size", [3, 7, 11])
def test_constant_importance_is_clipped_box_filter(size: int) -> None:
    x = torch.randn(2, 3, 8, 9, dtype=F64)
    imp = torch.full((2, 1, 8, 9), 4.2, dtype=F64)
    expect = _clipped_box_mean(x, size)
    for impl in ("fast", "reference"):
        torch.testing.assert_close(importance_filter(x, imp, size, impl=impl), expect, rtol=1e-12, atol=1e-12)


def test_box_sum_matches_pooling() -> None:
    x = torch.rand(2, 2, 7, 10, dtype=F64)
    ones = torch.ones_like(x)
    for size in (1, 3, 9, 21):
        expect = _clipped_box_mean(x, size) * _count(ones, size)
        torch.testing.assert_close(box_sum(x, size), expect, rtol=1e-12, atol=1e-12)


def test_box_sum_does_not_cancel() -> None:
    """A huge value early in a row must not wipe out the small ones after it: running-sum
    differences returned 0 for the windows past it (1e20 + 1 - 1e20 = 0)."""
    x = torch.ones(1, 1, 3, 20, dtype=F64)
    x[..., 1, 2] = 1e20
    out = box_sum(x, 3)
    far = out[..., 5:-1]  # past the big value, inside the image
    torch.testing.assert_close(far, torch.full_like(far, 9.0).index_fill_(-2, torch.tensor([0, 2]), 6.0), rtol=0, atol=0)


def _count(ones: torch.Tensor, size: int) -> torch.Tensor:
    return F.avg_pool2d(ones, size, stride=1, padding=size // 2, count_include_pad=True) * size * size


def test_size_one_and_dominant_pixel() -> None:
    g = torch.Generator().manual_seed(2)
    x = torch.randn(1, 3, 9, 9, generator=g, dtype=F64)
    imp = torch.randn(1, 1, 9, 9, generator=g, dtype=F64)
    # A 1 x 1 window is the identity whatever the importance.
    torch.testing.assert_close(importance_filter(x, imp, 1), x, rtol=0, atol=0)
    # One pixel with importance 60 above the rest: every window containing it returns its colour
    # up to exp(-60) * 25 relative; windows without it are untouched by it.
    imp2 = imp.clone()
    imp2[0, 0, 4, 4] = 60.0
    out = importance_filter(x, imp2, 5, impl="fast")
    near = out[0, :, 2:7, 2:7]
    torch.testing.assert_close(near, x[0, :, 4, 4, None, None].expand_as(near), rtol=1e-14, atol=1e-14)
    far = importance_filter_reference(x, imp, 5)[0, :, 0, 0]
    torch.testing.assert_close(out[0, :, 0, 0], far, rtol=1e-12, atol=1e-12)


def test_reference_kernels_sum_to_one_inside_image() -> None:
    imp = torch.randn(2, 1, 5, 6, dtype=F64)
    k = importance_kernel_reference(imp, 7)
    torch.testing.assert_close(k.sum(1), torch.ones(2, 5, 6, dtype=F64), rtol=1e-12, atol=1e-12)
    assert k[0, 0, 0, 0].item() == 0.0  # tap (-3, -3) from the top-left pixel is outside the image


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("impl,spread", [("reference", 1.0), ("fast", 1.0), ("fast", 60.0)])
def test_importance_gradcheck(device: str, impl: str, spread: float) -> None:
    """float64 gradcheck, for the fast path also with importances spread over 60 (the detached
    per-window shifts must cancel exactly in the gradient too)."""
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1, 1, 4, 5, generator=g, dtype=F64).to(device).requires_grad_()
    imp = (spread * torch.rand(1, 1, 4, 5, generator=g, dtype=F64)).to(device).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: importance_filter(a, b, 3, impl=impl), (x, imp))


def test_fused_gradcheck_and_matches_reference() -> None:
    g = torch.Generator().manual_seed(4)
    sizes = (3, 5)
    x = torch.randn(1, 2, 4, 5, generator=g, dtype=F64, requires_grad=True)
    imp = torch.randn(1, 2, 4, 5, generator=g, dtype=F64, requires_grad=True)
    fl = torch.randn(1, 2, 4, 5, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: fused_importance_filter(a, b, c, sizes), (x, imp, fl))
    fast = fused_importance_filter(x, imp, fl, sizes, impl="fast")
    ref = fused_importance_filter(x, imp, fl, sizes, impl="reference")
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)


def test_fused_selects_one_size_when_its_logit_dominates() -> None:
    g = torch.Generator().manual_seed(5)
    x = torch.randn(2, 3, 8, 8, generator=g, dtype=F64)
    imp = torch.randn(2, 6, 8, 8, generator=g, dtype=F64)
    fl = torch.zeros(2, 6, 8, 8, dtype=F64)
    fl[:, 2] = 1000.0  # size 7
    out = fused_importance_filter(x, imp, fl)
    torch.testing.assert_close(out, importance_filter(x, imp[:, 2:3], 7), rtol=1e-12, atol=1e-12)
    # Equal logits: the plain average of the six filtered images.
    avg = sum(importance_filter(x, imp[:, i : i + 1], s) for i, s in enumerate((3, 5, 7, 9, 11, 13))) / 6
    torch.testing.assert_close(fused_importance_filter(x, imp, torch.zeros_like(fl)), avg, rtol=1e-12, atol=1e-12)


def test_importance_bad_input() -> None:
    x = torch.zeros(2, 3, 8, 8)
    with pytest.raises(ValueError, match=r"importance must have shape \(B, 1, H, W\) = \(2, 1, 8, 8\)"):
        importance_filter(x, torch.zeros(2, 2, 8, 8), 3)
    with pytest.raises(ValueError, match="size must be a positive odd int"):
        importance_filter(x, torch.zeros(2, 1, 8, 8), 4)
    with pytest.raises(ValueError, match=r"image must have shape \(B, C, H, W\)"):
        importance_filter(torch.zeros(3, 8, 8), torch.zeros(2, 1, 8, 8), 3)
    with pytest.raises(ValueError, match=r"fusion_logits must have shape \(B, N=6, H, W\)"):
        fused_importance_filter(x, torch.zeros(2, 6, 8, 8), torch.zeros(2, 5, 8, 8))
