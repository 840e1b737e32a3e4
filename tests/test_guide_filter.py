"""The guide prefilter (mcdenoise/eval/guide_filter.py) and OIDN's ``-gf`` mode built on it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from mcdenoise.eval import guide_filter as gf
from mcdenoise.eval.guide_filter import GuideFilter, prefilter_guides, weights_digest
from mcdenoise.eval.oidn import oidn_available, oidn_denoise

needs_oidn = pytest.mark.skipif(not oidn_available(), reason="pyoidn not installed")


def _guides(h: int, w: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(1, 3, h, w, generator=g)
    n = torch.nn.functional.normalize(torch.randn(1, 3, h, w, generator=g), dim=1)
    return a, n


def _trained_like(seed: int = 1) -> GuideFilter:
    """A filter whose residual is not zero (random output layer), as after training."""
    torch.manual_seed(seed)
    net = GuideFilter()
    torch.nn.init.normal_(net.out.weight, std=0.1)
    return net.eval()


def test_an_untrained_filter_is_the_identity() -> None:
    """Catches a start that distorts the guides before any training (the residual must be 0)."""
    a, n = _guides(20, 28)
    fa, fn = GuideFilter()(a, n)
    assert torch.equal(fa, a) and torch.equal(fn, n)


@pytest.mark.parametrize("h,w", [(13, 7), (1, 1), (64, 66)])
def test_any_size_comes_back_at_its_size_and_matches_the_padded_image(h: int, w: int) -> None:
    """Catches the pad-to-4 and crop-back being off by a row or column: the output keeps the
    input's size, and its top-left part does not depend on how far the image extends."""
    net = _trained_like()
    a, n = _guides(h, w)
    with torch.no_grad():
        fa, fn = net(a, n)
    assert fa.shape == a.shape and fn.shape == n.shape and torch.isfinite(fa).all()


def test_constant_guides_stay_constant_far_from_the_border_after_training_like_weights() -> None:
    """Catches a filter that adds structure where there is none (a position-dependent bias from
    the padding reaching the middle of a flat image): a flat guide maps to a flat guide inside."""
    net = _trained_like()
    a = torch.full((1, 3, 32, 32), 0.4)
    n = torch.zeros(1, 3, 32, 32)
    n[:, 2] = 1.0
    with torch.no_grad():
        fa, fn = net(a, n)
    inner = (slice(None), slice(None), slice(8, 24), slice(8, 24))
    # per channel: each channel may move, but by the same amount at every inner pixel
    assert float(fa[inner].std(dim=(-2, -1)).max()) < 1e-5 and float(fn[inner].std(dim=(-2, -1)).max()) < 1e-5


def test_every_parameter_gets_a_gradient() -> None:
    """Catches a layer left out of the forward pass (it would never train)."""
    net = _trained_like()
    a, n = _guides(16, 16)
    fa, fn = net(a, n)
    (fa.square().mean() + fn.square().mean()).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and float(p.grad.abs().sum()) > 0, name


def test_prefilter_guides_clamps_to_the_guides_ranges() -> None:
    """Catches a negative albedo or a normal outside [-1, 1] reaching OIDN (whose guide filters
    never give those)."""
    net = _trained_like()
    torch.nn.init.normal_(net.out.weight, std=10.0)
    a, n = _guides(12, 12)
    fa, fn = prefilter_guides(a[0].numpy(), n[0].numpy(), net)
    assert fa.dtype == np.float32 and fa.min() >= 0 and np.abs(fn).max() <= 1


def test_the_cache_digest_follows_the_weights(tmp_path) -> None:
    """Catches a cache of ``oidn_gf`` images kept after the guide filter was retrained."""
    p = tmp_path / "g.safetensors"
    save_file(GuideFilter().state_dict(), str(p))
    d0 = weights_digest(p)
    save_file(_trained_like().state_dict(), str(p))
    assert weights_digest(p) != d0 and len(d0) == 12


@needs_oidn
def test_oidn_gf_with_albedo_alone_passes_the_guide_through() -> None:
    """Catches the -gf mode inventing a normal guide (the filter reads both) when only albedo is given."""
    a, _ = _guides(24, 24)
    color = np.random.default_rng(0).random((3, 24, 24), dtype=np.float32)
    np.testing.assert_array_equal(oidn_denoise(color, a[0].numpy(), prefilter="gf"),
                                  oidn_denoise(color, a[0].numpy()))


@needs_oidn
def test_oidn_gf_uses_the_filtered_guides(monkeypatch) -> None:
    """Catches ``prefilter='gf'`` being ignored: with a filter that replaces the guides, OIDN's
    output equals OIDN run on those replaced guides."""
    rng = np.random.default_rng(1)
    color = rng.random((3, 24, 24), dtype=np.float32)
    a, n = _guides(24, 24)
    flat_a = np.full((3, 24, 24), 0.5, np.float32)
    flat_n = np.zeros((3, 24, 24), np.float32)
    flat_n[2] = 1.0
    monkeypatch.setattr(gf, "prefilter_guides", lambda al, nr, net=None: (flat_a, flat_n))
    got = oidn_denoise(color, a[0].numpy(), n[0].numpy(), prefilter="gf")
    np.testing.assert_array_equal(got, oidn_denoise(color, flat_a, flat_n))
    assert not np.array_equal(got, oidn_denoise(color, a[0].numpy(), n[0].numpy()))
