"""Pyramid helpers, the layer paper's hierarchical filter (Eq. 10) and WSKP's multi-resolution blend (Eq. 7)."""

from __future__ import annotations

import pytest
import torch

from conftest import DEVICES

from mcdenoise.ops import (
    combine_levels,
    downsample2,
    gather,
    hierarchical_filter,
    multires_blend,
    softmax_kernel,
    upsample2,
)

F64 = torch.float64
SIZES = [(8, 8), (7, 9), (5, 6), (1, 1)]


def _delta(b: int, shape: tuple[int, int], k: int = 5) -> torch.Tensor:
    w = torch.zeros(b, k * k, *shape, dtype=F64)
    w[:, (k * k) // 2] = 1.0
    return w


def _pyr_sizes(h: int, w: int, n: int) -> list[tuple[int, int]]:
    out = [(h, w)]
    for _ in range(n - 1):
        h, w = (h + 1) // 2, (w + 1) // 2
        out.append((h, w))
    return out


@pytest.mark.parametrize("hw", SIZES)
def test_down_up_identities(hw: tuple[int, int]) -> None:
    h, w = hw
    x = torch.randn(2, 3, (h + 1) // 2, (w + 1) // 2, dtype=F64)
    up = upsample2(x, (h, w))
    assert up.shape == (2, 3, h, w)
    torch.testing.assert_close(downsample2(up), x, rtol=1e-15, atol=1e-15)


def test_downsample2_values() -> None:
    x = torch.arange(15, dtype=F64).reshape(1, 1, 3, 5)
    d = downsample2(x)
    # 2 x 2 means; the odd last row / column average only in-image pixels.
    expect = torch.tensor([[[[3.0, 5.0, 6.5], [10.5, 12.5, 14.0]]]], dtype=F64)
    torch.testing.assert_close(d, expect, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="not a 2x upsampling"):
        upsample2(d, (6, 5))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("hw", SIZES[:3])
def test_multires_blend_identities(device: str, hw: tuple[int, int]) -> None:
    h, w = hw
    g = torch.Generator().manual_seed(h * 31 + w)
    fine = torch.randn(2, 3, h, w, generator=g, dtype=F64).to(device)
    coarse = torch.randn(2, 3, (h + 1) // 2, (w + 1) // 2, generator=g, dtype=F64).to(device)
    alpha = torch.rand(2, 1, h, w, generator=g, dtype=F64).to(device)
    # Coarse = D(fine): nothing to replace, for any alpha.
    torch.testing.assert_close(multires_blend(fine, downsample2(fine), alpha), fine, rtol=1e-14, atol=1e-14)
    # alpha = 0 keeps fine; alpha = 1 puts exactly the coarse image in the low frequencies: D(out) = coarse.
    torch.testing.assert_close(multires_blend(fine, coarse, torch.zeros_like(alpha)), fine, rtol=0, atol=0)
    out1 = multires_blend(fine, coarse, torch.ones_like(alpha))
    torch.testing.assert_close(downsample2(out1), coarse, rtol=1e-13, atol=1e-13)
    # Eq. 7 term by term.
    expect = fine - alpha * upsample2(downsample2(fine), (h, w)) + alpha * upsample2(coarse, (h, w))
    torch.testing.assert_close(multires_blend(fine, coarse, alpha), expect, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("mode", ["gather", "splat"])
@pytest.mark.parametrize("hw", SIZES[:3])
def test_hierarchical_delta_kernels(mode: str, hw: tuple[int, int]) -> None:
    h, w = hw
    x = torch.randn(2, 3, h, w, dtype=F64)
    ws = [_delta(2, s) for s in _pyr_sizes(h, w, 3)]
    lam = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    torch.testing.assert_close(hierarchical_filter(x, ws, lam, mode=mode, eps=0.0), x, rtol=1e-14, atol=1e-14)
    lam = torch.tensor([0.0, 1.0, 0.0], dtype=F64)
    expect = upsample2(downsample2(x), (h, w))
    torch.testing.assert_close(hierarchical_filter(x, ws, lam, mode=mode, eps=0.0), expect, rtol=1e-14, atol=1e-14)


def test_hierarchical_matches_manual_composition_and_shapes_of_lambda() -> None:
    g = torch.Generator().manual_seed(7)
    x = torch.randn(2, 3, 9, 7, generator=g, dtype=F64)
    sizes = _pyr_sizes(9, 7, 3)
    ws = [softmax_kernel(torch.randn(2, 25, *s, generator=g, dtype=F64)) for s in sizes]
    lam = torch.rand(2, 3, generator=g, dtype=F64)
    x1 = downsample2(x)
    x2 = downsample2(x1)
    g0, g1, g2 = gather(x, ws[0]), gather(x1, ws[1]), gather(x2, ws[2])
    up1 = upsample2(g1, sizes[0])
    up2 = upsample2(upsample2(g2, sizes[1]), sizes[0])
    l = lam[:, :, None, None]
    expect = l[:, 0:1] * g0 + l[:, 1:2] * up1 + l[:, 2:3] * up2
    out = hierarchical_filter(x, ws, lam)
    torch.testing.assert_close(out, expect, rtol=1e-13, atol=1e-13)
    # Per-pixel lambdas that are constant reproduce the per-image ones; a 1-D lambda broadcasts.
    lam_map = lam[:, :, None, None].expand(2, 3, 9, 7)
    torch.testing.assert_close(hierarchical_filter(x, ws, lam_map), out, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(combine_levels([g0, g1, g2], lam), out, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(
        hierarchical_filter(x[:1], [w[:1] for w in ws], lam[0]), out[:1], rtol=1e-14, atol=1e-14
    )


def test_hierarchical_constant_image_splat_normalised() -> None:
    # Splat mode normalises each level, so a constant stays constant (borders included) when the
    # lambdas sum to one.
    g = torch.Generator().manual_seed(8)
    x = torch.full((1, 3, 11, 10), 0.7, dtype=F64)
    ws = [torch.rand(1, 25, *s, generator=g, dtype=F64) for s in _pyr_sizes(11, 10, 3)]
    lam = torch.tensor([0.5, 0.3, 0.2], dtype=F64)
    torch.testing.assert_close(hierarchical_filter(x, ws, lam, mode="splat", eps=0.0), x, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("mode", ["gather", "splat"])
def test_multiscale_gradcheck(device: str, mode: str) -> None:
    g = torch.Generator().manual_seed(9)
    sizes = _pyr_sizes(5, 4, 3)
    x = torch.randn(1, 1, 5, 4, generator=g, dtype=F64).to(device).requires_grad_()
    ws = [torch.rand(1, 9, *s, generator=g, dtype=F64).add(0.1).to(device).requires_grad_() for s in sizes]
    lam = torch.rand(1, 3, generator=g, dtype=F64).to(device).requires_grad_()
    # fast_mode (random projections of the Jacobian): the ops inside are fully gradchecked in
    # their own tests, this checks the composition and keeps the test at about a second.
    assert torch.autograd.gradcheck(
        lambda a, w0, w1, w2, l: hierarchical_filter(a, [w0, w1, w2], l, mode=mode), (x, *ws, lam), fast_mode=True
    )
    fine = torch.randn(1, 2, 3, 5, generator=g, dtype=F64).to(device).requires_grad_()
    coarse = torch.randn(1, 2, 2, 3, generator=g, dtype=F64).to(device).requires_grad_()
    alpha = torch.rand(1, 1, 3, 5, generator=g, dtype=F64).to(device).requires_grad_()
    assert torch.autograd.gradcheck(multires_blend, (fine, coarse, alpha))


def test_multiscale_bad_input() -> None:
    x = torch.zeros(1, 3, 8, 8)
    ws = [torch.zeros(1, 25, 8, 8), torch.zeros(1, 25, 4, 4), torch.zeros(1, 25, 3, 3)]
    with pytest.raises(ValueError, match=r"weights\[2\] must have shape \(B, K\*K, H_i, W_i\) = \(1, K\*K, 2, 2\)"):
        hierarchical_filter(x, ws, torch.ones(3))
    ws[2] = torch.zeros(1, 25, 2, 2)
    with pytest.raises(ValueError, match=r"level_weights must have shape"):
        hierarchical_filter(x, ws, torch.ones(4))
    with pytest.raises(ValueError, match="mode must be"):
        hierarchical_filter(x, ws, torch.ones(3), mode="blend")
    with pytest.raises(ValueError, match=r"coarse must have shape .* = \(1, 3, 4, 4\)"):
        multires_blend(x, torch.zeros(1, 3, 3, 4), torch.zeros(1, 1, 8, 8))
    with pytest.raises(ValueError, match=r"alpha must have shape \(B, 1, H, W\)"):
        multires_blend(x, torch.zeros(1, 3, 4, 4), torch.zeros(1, 1, 4, 4))
