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


# --- One shift per image, box sums of exp(I - M), exact fallback (issue: WSKP CPU speed) ---------

from mcdenoise.ops import importance_fast as imp_mod  # noqa: E402  (the fast path's internals)

PAPER = (3, 5, 7, 9, 11, 13)


@pytest.fixture
def count_exact(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Counts the calls of the exact per-window-shifted fallback."""
    calls = [0]
    exact = imp_mod._filter_exact

    def counted(*args: object) -> torch.Tensor:
        calls[0] += 1
        return exact(*args)

    monkeypatch.setattr(imp_mod, "_filter_exact", counted)
    return calls


@pytest.fixture
def no_exact(monkeypatch: pytest.MonkeyPatch) -> None:
    def forbidden(*args: object) -> torch.Tensor:
        raise AssertionError("the exact fallback ran on ordinary input")

    monkeypatch.setattr(imp_mod, "_filter_exact", forbidden)


def _fast_both_paths(x: torch.Tensor, imp: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The no-autograd (banded on the CPU) and the autograd (whole-tensor) fast paths."""
    with torch.no_grad():
        banded = importance_filter(x, imp, size, impl="fast")
    whole = importance_filter(x.requires_grad_(), imp, size, impl="fast").detach()
    x.requires_grad_(False)
    return banded, whole


@pytest.mark.parametrize("rows", [3, 8, 64])
@pytest.mark.parametrize("size", [3, 5, 7, 9, 11, 13, 15])
def test_one_shift_matches_reference_float64(monkeypatch: pytest.MonkeyPatch, no_exact: None, rows: int, size: int) -> None:
    """Catches a wrong offset in the power-of-two box sums (13 = 8 + 4 + 1) or in a band's halo
    rows and zero margins (a band of 3 rows has halos wider than itself): both fast paths equal
    the unfold + softmax reference in float64, without the fallback."""
    monkeypatch.setattr(imp_mod, "_band_rows", lambda h, w: rows)
    g = torch.Generator().manual_seed(size * 100 + rows)
    x = torch.randn(2, 3, 19, 23, generator=g, dtype=F64)
    imp = 4 * torch.randn(2, 1, 19, 23, generator=g, dtype=F64)
    ref = importance_filter_reference(x, imp, size)
    for out in _fast_both_paths(x, imp, size):
        torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("rows", [4, 64])
@pytest.mark.parametrize("sizes", [PAPER, (7, 1, 3)])
def test_fused_one_shift_matches_reference_float64(monkeypatch: pytest.MonkeyPatch, no_exact: None, rows: int, sizes: tuple[int, ...]) -> None:
    """Catches a mix-up of maps, fusion weights or per-size halos in the fused banded pass (N
    filters in one loop over bands; unsorted sizes and the identity size 1 included)."""
    monkeypatch.setattr(imp_mod, "_band_rows", lambda h, w: rows)
    g = torch.Generator().manual_seed(rows)
    n = len(sizes)
    x = torch.randn(2, 3, 17, 21, generator=g, dtype=F64)
    imp = 3 * torch.randn(2, n, 17, 21, generator=g, dtype=F64)
    fl = torch.randn(2, n, 17, 21, generator=g, dtype=F64)
    ref = fused_importance_filter(x, imp, fl, sizes, impl="reference")
    with torch.no_grad():
        fast = fused_importance_filter(x, imp, fl, sizes, impl="fast")
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)


def _dim_patch(h: int, w: int, rows: slice, cols: slice, depth: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(2, 3, h, w, generator=g, dtype=F64)
    imp = 5 * torch.rand(2, 1, h, w, generator=g, dtype=F64)
    imp[..., rows, cols] -= depth
    return x, imp


@pytest.mark.parametrize("rows", [5, 64])
@pytest.mark.parametrize("patch", [(slice(12, None), slice(None)), (slice(9, 16), slice(3, 9)), (slice(0, 4), slice(None))])
def test_fallback_where_windows_are_far_below_the_image_max_float64(
    monkeypatch: pytest.MonkeyPatch, count_exact: list[int], rows: int, patch: tuple[slice, slice]
) -> None:
    """Importances 1000 below the image maximum (the lower half, a 7 x 6 patch, the top 4 rows):
    exp(I - M) underflows there even in float64 (e^-1000), so the windows wholly inside
    (k = 5) would be 0/0 with an image-wide shift alone.  Catches a missing or misplaced fallback
    (crop, halo, band rows of its mask): the result equals the reference, and the fallback ran."""
    monkeypatch.setattr(imp_mod, "_band_rows", lambda h, w: rows)
    rs, cs = patch
    x, imp = _dim_patch(24, 18, rs, cs, 1000.0, 7)
    ref = importance_filter_reference(x, imp, 5)
    for out in _fast_both_paths(x, imp, 5):
        torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    assert count_exact[0] == 2  # once per path


def test_fused_fallback_in_two_separate_bands_float64(monkeypatch: pytest.MonkeyPatch, count_exact: list[int]) -> None:
    """Two dim 4 x 4 patches in bands far apart (rows of 4), in the size-3 map of six: catches a
    fallback that patches only the first flagged band or offsets the second."""
    monkeypatch.setattr(imp_mod, "_band_rows", lambda h, w: 4)
    g = torch.Generator().manual_seed(8)
    x = torch.rand(1, 3, 30, 12, generator=g, dtype=F64)
    imp = 2 * torch.randn(1, 6, 30, 12, generator=g, dtype=F64)
    imp[:, 0, 2:6, 1:5] -= 2000
    imp[:, 0, 23:27, 7:11] -= 2000
    fl = torch.randn(1, 6, 30, 12, generator=g, dtype=F64)
    ref = fused_importance_filter(x, imp, fl, impl="reference")
    with torch.no_grad():
        fast = fused_importance_filter(x, imp, fl, impl="fast")
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    assert count_exact[0] == 1


@pytest.mark.parametrize("grad", [False, True])
def test_float32_importance_spanning_1e3_is_finite(count_exact: list[int], grad: bool) -> None:
    """float32 importances uniform over [0, 1000]: most windows lie far below the image maximum
    (exp(I - M) is 0 in float32).  Catches 0/0 = NaN or inf there, forward and backward."""
    g = torch.Generator().manual_seed(9)
    x = torch.rand(1, 3, 40, 40, generator=g)
    imp = 1000 * torch.rand(1, 1, 40, 40, generator=g)
    xi, ii = x.clone().requires_grad_(grad), imp.clone().requires_grad_(grad)
    with torch.set_grad_enabled(grad):
        out = importance_filter(xi, ii, 7, impl="fast")
    assert torch.isfinite(out).all() and count_exact[0] == 1
    ref = importance_filter_reference(x.double(), imp.double(), 7)
    torch.testing.assert_close(out.double(), ref, rtol=1e-5, atol=1e-5)
    if grad:
        out.square().sum().backward()
        assert torch.isfinite(xi.grad).all() and torch.isfinite(ii.grad).all()
    fl = torch.randn(1, 6, 40, 40, generator=g)
    imp6 = 1000 * torch.rand(1, 6, 40, 40, generator=g)
    with torch.set_grad_enabled(grad):
        fused = fused_importance_filter(x, imp6.requires_grad_(grad), fl, impl="fast")
    assert torch.isfinite(fused).all()
    torch.testing.assert_close(fused.double(), fused_importance_filter(x.double(), imp6.double(), fl.double(), impl="reference"), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("dim_rows", [None, slice(0, 3), slice(None)])
def test_one_shift_gradcheck(count_exact: list[int], dim_rows: slice | None) -> None:
    """float64 gradcheck of the autograd fast path: ordinary importances, the first rows 1000
    below the rest (fallback on part of the image: the torch.where must pass gradients to both
    sides and no inf/NaN from the replaced denominators), and all of it (fallback everywhere
    except the windows near the maximum)."""
    g = torch.Generator().manual_seed(10)
    x = torch.randn(1, 2, 6, 5, generator=g, dtype=F64)
    imp = 3 * torch.rand(1, 1, 6, 5, generator=g, dtype=F64)
    if dim_rows is not None:
        n = imp[..., dim_rows, :].shape[-2]  # each dim row 1000 below the one above it
        imp[..., dim_rows, :] -= 1000 * torch.arange(1, n + 1, dtype=F64)[:, None]
    assert torch.autograd.gradcheck(
        lambda a, b: importance_filter(a, b, 3, impl="fast"), (x.requires_grad_(), imp.requires_grad_())
    )
    assert (count_exact[0] > 0) == (dim_rows is not None)


def test_fallback_not_taken_for_ordinary_input(no_exact: None) -> None:
    """Catches a fallback threshold that fires on ordinary input (the slow exact path would run
    on every frame): float32 importances spread over 50 and the folded wskp paper model run
    without it, with and without autograd."""
    from mcdenoise.models.registry import build_model, synthetic_batch

    g = torch.Generator().manual_seed(11)
    x = torch.rand(1, 3, 48, 40, generator=g)
    imp = 50 * torch.rand(1, 6, 48, 40, generator=g)
    fl = torch.randn(1, 6, 48, 40, generator=g)
    with torch.no_grad():
        fused_importance_filter(x, imp, fl)
        importance_filter(x, imp[:, :1], 13)
    fused_importance_filter(x, imp.requires_grad_(), fl).sum().backward()
    model = build_model("wskp", "paper").reparameterize()
    with torch.inference_mode():
        assert torch.isfinite(model(synthetic_batch(model, height=40, width=48))).all()
