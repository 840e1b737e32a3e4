"""The one luminance helper (mcdenoise.color) gives exactly what the three copies it replaced gave:
the procedural preview's ``img @ w`` (exposure of every dataset image depends on it), the crop
sampler's channel-first ``tensordot`` and KPCN's torch weighted sum."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mcdenoise.color import LUMINANCE_WEIGHTS, luminance

W = (0.2126, 0.7152, 0.0722)


def test_weights_are_rec709() -> None:
    assert LUMINANCE_WEIGHTS == W


def test_numpy_matches_the_replaced_expressions_bit_for_bit() -> None:
    rng = np.random.default_rng(0)
    img = rng.lognormal(size=(17, 23, 3))  # preview: (H, W, 3) float64
    assert np.array_equal(luminance(img), img @ np.array(W))
    chw = rng.lognormal(size=(3, 19, 11)).astype(np.float32).astype(np.float64)  # sampler: (3, H, W)
    assert np.array_equal(luminance(chw, 0), np.tensordot(np.array(W, np.float64), chw, axes=1))
    assert luminance(chw, 0, keepdims=True).shape == (1, 19, 11)
    mid = np.moveaxis(chw, 0, 1)  # (H, 3, W)
    assert np.allclose(luminance(mid, 1), luminance(chw, 0), rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_torch_matches_the_replaced_expression(dtype: torch.dtype) -> None:
    x = torch.rand(2, 3, 5, 7, generator=torch.Generator().manual_seed(0), dtype=dtype)
    want = (x * x.new_tensor(W).view(1, 3, 1, 1)).sum(dim=1, keepdim=True)
    got = luminance(x, 1, keepdims=True)
    assert got.dtype == dtype and torch.equal(got, want)


def test_wrong_channel_count_is_refused() -> None:
    with pytest.raises(ValueError, match="3 \\(RGB\\)"):
        luminance(np.zeros((4, 4, 4)))
