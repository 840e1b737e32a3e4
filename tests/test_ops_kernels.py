"""Max-shifted kernel exponentials (ops/kernels.py): exact normalisation however peaked the kernels.

The models divide by ``weight_sum + eps`` with eps = 1e-8 (SBMCConfig.eps). A max shift that does
not make the largest weight reaching each output pixel exactly 1 lets that sum fall below eps once
training makes kernels peaked (logit gaps of 25 and more), and pixels go dark or black (issue 8,
bug 1). Every test here compares with a float64 normalisation done without any shift.
"""

from __future__ import annotations

import pytest
import torch

from mcdenoise.models.sbmc import SBMCConfig
from mcdenoise.ops.gather import gather, gather_rows
from mcdenoise.ops.kernels import destination_max, per_destination_exp, per_pixel_exp
from mcdenoise.ops.splat import normalize_splat, splat, splat_into_, splat_reference

F64 = torch.float64
EPS = SBMCConfig().eps  # the models' real eps, not 0


def peaked_logits(gap: float, *, b: int = 1, s: int = 2, k: int = 5, h: int = 10, w: int = 11,
                  seed: int = 0) -> torch.Tensor:
    """Random logits (std 1) where every sample of every other pixel puts ``gap`` on one random
    tap: the peaks land on some pixels while their neighbours get only ordinary taps."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(b, s, k * k, h, w, generator=g, dtype=F64)
    peak = torch.randint(0, k * k, (b, s, 1, h, w), generator=g)
    on = torch.zeros(b, s, 1, h, w, dtype=torch.bool)
    on[..., ::2, :] = True
    return x + gap * torch.zeros_like(x).scatter_(2, peak, 1.0) * on


def exact_splat(values: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """Eq. 1 in float64 with plain ``exp`` (no shift) and no eps: the ground truth."""
    num, wsum = splat_reference(values.to(F64), torch.exp(logits.to(F64)))
    return num / wsum


@pytest.mark.parametrize("gap", [25.0, 80.0])
def test_peaked_splat_kernels_normalise_exactly_with_model_eps(gap: float) -> None:
    """Catches: shifting by the max of any sample within K x K of the destination (the old bound),
    which left the weight landing next to a peak at exp(-gap) < eps: dark or black pixels."""
    logits = peaked_logits(gap)
    values = torch.rand(1, 2, 3, 10, 11, generator=torch.Generator().manual_seed(1), dtype=F64) + 0.5
    want = exact_splat(values, logits)
    lg = logits.float()
    num, wsum = splat(values.float(), per_destination_exp(lg, 5))
    got = normalize_splat(num, wsum, EPS)
    torch.testing.assert_close(got.double(), want, rtol=2e-5, atol=0)
    assert float(wsum.min()) >= 1.0 - 1e-6  # the largest landing weight is exactly 1


@pytest.mark.parametrize("gap", [25.0, 80.0])
def test_peaked_splat_gradients_are_finite_and_exact(gap: float) -> None:
    """Catches: an overflowing or underflowing shift in the backward pass (inf/NaN gradients), and a
    shift that does not cancel (wrong gradients)."""
    logits = peaked_logits(gap, s=2, k=3, h=6, w=7)
    values = torch.rand(1, 2, 3, 6, 7, generator=torch.Generator().manual_seed(2), dtype=F64)
    lg64 = logits.clone().requires_grad_(True)
    exact_splat(values, lg64).square().sum().backward()
    lg32 = logits.float().requires_grad_(True)
    num, wsum = splat(values.float(), per_destination_exp(lg32, 3))
    normalize_splat(num, wsum, EPS).square().sum().backward()
    assert torch.isfinite(lg32.grad).all()
    torch.testing.assert_close(lg32.grad.double(), lg64.grad, rtol=1e-3, atol=1e-5)


def test_destination_max_is_the_max_over_the_taps_that_land() -> None:
    """Catches: an off-by-one or flipped tap offset in the per-tap shift (would still be an upper
    bound on some pixels, so the splat tests alone could miss it)."""
    b, s, k, h, w = 1, 3, 3, 5, 6
    r = k // 2
    logits = torch.randn(b, s, k * k, h, w, generator=torch.Generator().manual_seed(4), dtype=F64)
    plane = destination_max(logits, k)
    want = torch.full((b, h + 2 * r, w + 2 * r), float("-inf"), dtype=F64)
    for i in range(k):
        for j in range(k):
            for y in range(h):
                for x in range(w):
                    u = (y + i - r + r, x + j - r + r)  # destination, in padded coordinates
                    want[0, u[0], u[1]] = max(want[0, u[0], u[1]], logits[0, :, i * k + j, y, x].max())
    assert torch.equal(plane, want)


def test_chunks_and_row_bands_share_one_exact_shift() -> None:
    """Catches: a shift computed per chunk of samples or per band of rows (no longer one constant
    per destination, so chunked and banded inference would differ from the whole)."""
    k, h, w = 5, 12, 9
    logits = peaked_logits(40.0, s=4, k=k, h=h, w=w, seed=5)
    values = torch.rand(1, 4, 3, h, w, generator=torch.Generator().manual_seed(6), dtype=F64)
    whole = normalize_splat(*splat(values, per_destination_exp(logits, k)), EPS)
    plane = None
    for s0 in (0, 3):  # chunks of samples
        plane = destination_max(logits[:, s0 : s0 + 3], k, plane=plane)
    r = k // 2
    acc = torch.zeros(1, 4, h + 2 * r, w + 2 * r, dtype=F64)
    for y0, y1 in ((0, 5), (5, 6), (6, 12)):  # bands of rows, splatted into one padded accumulator
        wts = per_destination_exp(logits[..., y0:y1, :], k, plane, row0=y0)
        splat_into_(values[..., y0:y1, :], wts, acc, row0=y0)
    banded = normalize_splat(acc[:, :3, r : r + h, r : r + w], acc[:, 3:, r : r + h, r : r + w], EPS)
    torch.testing.assert_close(banded, whole, rtol=1e-12, atol=0)
    torch.testing.assert_close(banded, exact_splat(values, logits), rtol=3 * EPS, atol=0)  # eps vs wsum >= 1


def test_banded_destination_max_equals_whole() -> None:
    """Catches: a wrong row offset when the per-destination max is accumulated band by band."""
    k = 5
    logits = peaked_logits(30.0, s=2, k=k, h=11, w=8, seed=7)
    whole = destination_max(logits, k)
    plane = None
    for y0, y1 in ((0, 4), (4, 11)):
        if plane is None:
            plane = torch.full_like(whole, float("-inf"))
        destination_max(logits[..., y0:y1, :], k, plane=plane, row0=y0)
    assert torch.equal(plane, whole)


@pytest.mark.parametrize("gap", [25.0, 80.0])
def test_peaked_gather_kernels_at_the_border_normalise_exactly(gap: float) -> None:
    """Catches: a per-pixel max taken over taps that read outside the image (zero padding): when
    such a tap holds the peak, the in-image weights are all below exp(-gap) and border pixels go
    black (the failure of pixel_gather and sbmc_gather with parameters x2/x3)."""
    k, h, w = 5, 8, 9
    logits = peaked_logits(gap, s=2, k=k, h=h, w=w, seed=8)
    logits[..., 0, :, :] += gap  # tap (0, 0) reads up-left: outside the image on the first rows
    img = torch.rand(1, 2, 3, h, w, generator=torch.Generator().manual_seed(9), dtype=F64) + 0.5
    ones = torch.cat([img, torch.ones_like(img[:, :, :1])], dim=2).reshape(2, 4, h, w)

    def normalised(wts: torch.Tensor) -> torch.Tensor:
        out = gather(ones.to(wts.dtype), wts.reshape(2, k * k, h, w)).reshape(1, 2, 4, h, w).sum(1)
        return out[:, :3] / (out[:, 3:] + (EPS if wts.dtype == torch.float32 else 0.0))

    want = normalised(torch.exp(logits))
    got = normalised(per_pixel_exp(logits.float()))
    torch.testing.assert_close(got.double(), want, rtol=2e-5, atol=0)


def test_gather_rows_equals_gather() -> None:
    """Catches: wrong halo rows (or zero padding) when a gather is done one band of rows at a time."""
    g = torch.Generator().manual_seed(10)
    img = torch.randn(2, 3, 9, 7, generator=g, dtype=F64)
    wts = torch.randn(2, 25, 9, 7, generator=g, dtype=F64)
    whole = gather(img, wts)
    for y0, y1 in ((0, 1), (1, 4), (4, 9), (2, 3)):
        torch.testing.assert_close(gather_rows(img, wts[..., y0:y1, :], y0), whole[..., y0:y1, :], rtol=1e-12, atol=1e-12)


def test_per_pixel_exp_row_band_masks_image_rows_not_band_rows() -> None:
    """Catches: treating a band's first row as the image's first row (would mask in-image taps)."""
    logits = torch.randn(1, 2, 9, 6, 5, generator=torch.Generator().manual_seed(11), dtype=F64)
    whole = per_pixel_exp(logits)
    torch.testing.assert_close(per_pixel_exp(logits[..., 2:4, :], row0=2, height=6), whole[..., 2:4, :])


def test_inplace_exponentials_give_the_same_values_and_gradients() -> None:
    """Catches: an in-place shift that breaks autograd or changes the result."""
    g = torch.Generator().manual_seed(12)
    src = torch.randn(1, 2, 9, 5, 6, generator=g, dtype=F64, requires_grad=True)
    vals = torch.rand(1, 2, 3, 5, 6, generator=g, dtype=F64)
    for fn in (lambda x, **kw: per_destination_exp(x, 3, **kw), per_pixel_exp):
        ref = fn(src * 1.0)
        (gref,) = torch.autograd.grad((ref * vals[:, :, :1]).sum(), src)
        got = fn(src * 1.0, inplace=True)  # src * 1.0: a non-leaf nobody saved, like a conv output
        (ggot,) = torch.autograd.grad((got * vals[:, :, :1]).sum(), src)
        torch.testing.assert_close(got, ref)
        torch.testing.assert_close(ggot, gref)
