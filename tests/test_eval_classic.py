"""Feature-guided NL-means (mcdenoise/eval/classic.py), the non-learned baseline of `mcdenoise eval`."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import DEVICES
from mcdenoise.data.format import pixel_stats
from mcdenoise.eval.classic import FeatureNLMeans, NLMeansParams, feature_nlmeans
from mcdenoise.eval.metrics import relmse


def _scene(spp: int, size: int = 40, seed: int = 0) -> dict[str, np.ndarray]:
    """Two albedo regions with a smooth light gradient; samples = reference x gamma noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    albedo = np.where(xx < 0.5, 0.2, 0.8)[None].repeat(3, 0)
    albedo[1] *= 0.7
    ref = albedo * (0.5 + yy)[None]
    noise = rng.gamma(1.0, 1.0, size=(spp, 1, size, size))
    samples = ref[None] * noise
    mean, var = pixel_stats(samples)
    normal = np.zeros((3, size, size), np.float32)
    normal[2] = 1.0
    return {"ref": ref.astype(np.float32), "mean": mean, "var": var, "albedo": albedo.astype(np.float32), "normal": normal}


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a))


@pytest.mark.parametrize("with_variance", [True, False])
def test_reduces_error_on_noisy_image(with_variance: bool) -> None:
    """Catches a filter that does not denoise (weights collapsing onto the centre pixel, a sign
    error in the variance cancellation) or that blurs across the albedo edge."""
    s = _scene(8)
    out = feature_nlmeans(_t(s["mean"]), variance=_t(s["var"]) if with_variance else None,
                          albedo=_t(s["albedo"]), normal=_t(s["normal"]))
    before = relmse(s["mean"], s["ref"])
    after = relmse(out.numpy(), s["ref"])
    assert after < 0.25 * before, (before, after)


@pytest.mark.parametrize("device", DEVICES)
def test_constant_image_stays_constant(device: str) -> None:
    """Catches unnormalised weights or a border (padding) bias: any weights average a constant to itself."""
    g = torch.Generator().manual_seed(1)
    color = torch.full((3, 20, 24), 0.7, dtype=torch.float64)
    var = torch.rand((3, 20, 24), generator=g, dtype=torch.float64) * 0.1
    albedo = torch.rand((3, 20, 24), generator=g, dtype=torch.float64)
    normal = torch.nn.functional.normalize(torch.randn((3, 20, 24), generator=g, dtype=torch.float64), dim=0)
    out = feature_nlmeans(color.to(device), variance=var, albedo=albedo, normal=normal)
    assert out.dtype == torch.float64 and out.device.type == device
    torch.testing.assert_close(out.cpu(), color, rtol=0, atol=1e-12)


def test_batch_matches_single_images_and_module() -> None:
    """Catches images of a batch leaking into each other, and the module form drifting from the function."""
    a, b = _scene(4, seed=2), _scene(4, seed=3)
    col = torch.stack([_t(a["mean"]), _t(b["mean"])])
    var = torch.stack([_t(a["var"]), _t(b["var"])])
    alb = torch.stack([_t(a["albedo"]), _t(b["albedo"])])
    p = NLMeansParams(radius=3)
    both = FeatureNLMeans(p)(col, var, alb)
    one = feature_nlmeans(col[1], variance=var[1], albedo=alb[1], params=p)
    torch.testing.assert_close(both[1], one)


def test_zero_variance_falls_back_to_squared_colour() -> None:
    """One sample gives an all-zero variance: taken literally, the colour term would keep every
    pixel as it is; the fallback (``V = u^2``) must be used for it as for no variance at all."""
    s = _scene(1)
    zero = np.zeros_like(s["var"])
    out0 = feature_nlmeans(_t(s["mean"]), variance=_t(zero), albedo=_t(s["albedo"]))
    out_none = feature_nlmeans(_t(s["mean"]), albedo=_t(s["albedo"]))
    torch.testing.assert_close(out0, out_none)
    assert relmse(out0.numpy(), s["ref"]) < 0.5 * relmse(s["mean"], s["ref"])


def test_bad_shapes_name_the_expected_shape() -> None:
    """Catches a guide of the wrong size silently broadcasting."""
    c = torch.rand(3, 8, 8)
    with pytest.raises(ValueError, match=r"albedo must be \(B, 3, 8, 8\)"):
        feature_nlmeans(c, albedo=torch.rand(3, 8, 9))
    with pytest.raises(ValueError, match="variance"):
        feature_nlmeans(c, variance=torch.rand(1, 8, 8))
    with pytest.raises(ValueError, match="sigmas"):
        feature_nlmeans(c, params=NLMeansParams(sigma_albedo=0.0))
