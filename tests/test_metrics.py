"""Metrics against hand-computed values and scikit-image's SSIM."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mcdenoise.eval import metrics as M
from mcdenoise.io.exr import tonemap as preview_tonemap

# Hand-computed cases: one channel, 1x2 pixels.
X = np.array([[[1.0, 3.0]]])
Y = np.array([[[2.0, 3.0]]])


def test_hand_computed_values():
    assert M.mse(X, Y) == pytest.approx(0.5)  # (1 + 0) / 2
    assert M.relmse(X, Y) == pytest.approx((1 / (4 + 1e-2)) / 2)
    assert M.relmse(X, Y, eps=1.0) == pytest.approx((1 / 5) / 2)
    assert M.smape(X, Y) == pytest.approx((1 / (1 + 2 + 1e-2)) / 2)
    assert M.l1(X, Y) == pytest.approx(0.5)
    assert M.rel_l1(X, Y) == pytest.approx((1 / (2 + 1e-2)) / 2)
    # PSNR without tonemap: peak 1, mse 0.5 -> 10 log10(2).
    assert M.psnr(X, Y, tonemap_kind="none") == pytest.approx(10 * math.log10(2))
    # Reinhard tonemap: 1 -> srgb(0.5), 2 -> srgb(2/3); 3 == 3.
    srgb = lambda u: 1.055 * u ** (1 / 2.4) - 0.055  # noqa: E731
    e = (srgb(0.5) - srgb(2 / 3)) ** 2 / 2
    assert M.psnr(X, Y) == pytest.approx(-10 * math.log10(e))
    assert M.psnr(Y, Y) == math.inf


def test_channel_and_batch_averaging_and_border():
    rng = np.random.default_rng(0)
    x = rng.random((2, 3, 8, 8))
    y = rng.random((2, 3, 8, 8))
    per = M.mse(x, y, reduction="none")
    assert per.shape == (2,)
    np.testing.assert_allclose(per, ((x - y) ** 2).reshape(2, -1).mean(1))
    assert M.mse(x, y) == pytest.approx(per.mean())
    assert M.mse(x, y, border=2) == pytest.approx(((x - y)[..., 2:-2, 2:-2] ** 2).mean())
    # Per-channel relative error, not luminance: a channel with y = 0 weighs by 1/eps.
    y0 = np.zeros((3, 1, 1))
    x0 = np.array([0.1, 0.0, 0.0]).reshape(3, 1, 1)
    assert M.relmse(x0, y0) == pytest.approx(0.01 / 0.01 / 3)
    with pytest.raises(ValueError, match="shape"):
        M.mse(x, y[:, :2])
    with pytest.raises(ValueError, match="border"):
        M.mse(x, y, border=4)
    with pytest.raises(TypeError):
        M.mse(x, torch.from_numpy(y))


def _fixture_images() -> tuple[np.ndarray, np.ndarray]:
    """HDR reference with edges, a bright highlight and texture; the estimate adds noise and blur."""
    yy, xx = np.mgrid[0:48, 0:40] / 40.0
    ref = np.stack([np.sin(6 * xx) ** 2 + (xx > 0.5) * 2.0, yy * 3.0, 0.2 + 5.0 * np.exp(-((xx - 0.3) ** 2 + (yy - 0.6) ** 2) * 50)])
    rng = np.random.default_rng(42)
    est = ref * (1 + 0.3 * rng.standard_normal(ref.shape)) + 0.05 * rng.standard_normal(ref.shape)
    return est, ref


def test_ssim_matches_scikit_image():
    from skimage.metrics import structural_similarity

    est, ref = _fixture_images()
    for kind in ("reinhard", "srgb", "log"):
        a, b = M.tonemap(est, kind), M.tonemap(ref, kind)
        want = structural_similarity(a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                                     data_range=1.0, channel_axis=0)
        got = M.ssim(est, ref, tonemap_kind=kind)
        assert got == pytest.approx(want, abs=1e-10)
        assert 0.2 < got < 0.99  # a real, non-trivial comparison
    assert M.dssim(est, ref) == pytest.approx(1 - M.ssim(est, ref))
    assert M.ssim(ref, ref) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="at least 11x11"):
        M.ssim(est[:, :10, :10], ref[:, :10, :10])


def test_torch_matches_numpy_and_is_differentiable():
    est, ref = _fixture_images()
    x = torch.tensor(est, requires_grad=True)
    y = torch.tensor(ref)
    for name, fn in M.METRICS.items():
        if name == "flip":
            continue
        got = fn(x, y)
        assert isinstance(got, torch.Tensor) and got.ndim == 0
        assert got.item() == pytest.approx(fn(est, ref), rel=1e-12), name
    M.ssim(x, y).backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
    # float32 inputs stay float32.
    assert M.smape(x.detach().float(), y.float()).dtype == torch.float32


def test_gradcheck_float64():
    rng = np.random.default_rng(1)
    x = torch.tensor(rng.random((1, 1, 11, 12)) * 2, requires_grad=True)
    y = torch.tensor(rng.random((1, 1, 11, 12)) * 2)
    for fn in (M.ssim, M.smape, M.relmse, M.psnr):
        assert torch.autograd.gradcheck(lambda t: fn(t, y), (x,), eps=1e-6, atol=1e-6), fn.__name__


def test_tonemap_matches_preview_tonemap():
    v = np.array([-1.0, 0.0, 0.001, 0.2, 1.0, 7.0, 1e4]).reshape(1, 1, 7)
    for kind in ("srgb", "reinhard", "log"):
        np.testing.assert_allclose(M.tonemap(v, kind), preview_tonemap(v, kind=kind), atol=1e-12)
    assert M.tonemap(v, "none") is v


@pytest.mark.skipif(not M.flip_available(), reason="flip-evaluator not installed")
def test_flip():
    est, ref = _fixture_images()
    same = M.flip(ref, ref)
    worse = M.flip(est, ref)
    better = M.flip(0.8 * ref + 0.2 * est, ref)
    assert same == pytest.approx(0.0, abs=1e-6)
    assert 0.0 < better < worse < 1.0
    assert "flip" in M.METRICS


def test_compute_metrics():
    est, ref = _fixture_images()
    out = M.compute_metrics(est, ref, ["mse", "dssim"])
    assert set(out) == {"mse", "dssim"} and all(isinstance(v, float) for v in out.values())
    with pytest.raises(KeyError, match="unknown metric"):
        M.compute_metrics(est, ref, ["nope"])
