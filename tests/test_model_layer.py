"""Layer-embedding denoiser: partitioning (Eq. 2), compositing (Eq. 3-6), invariance, any L."""

from __future__ import annotations

import pytest
import torch

from mcdenoise.models.blocks import FCStack
from mcdenoise.models.registry import build_model, synthetic_batch
from mcdenoise.ops.splat import splat_reference

from test_model_sbmc import permute_samples, rel_diff, set_identity_kernel

NAMES = ("layer", "layer_weighted", "layer_optimized")


def identity_kernels(model) -> None:
    k = model.config.kernel_size
    if model.config.hierarchical:
        for g in model.kernel_gens:
            set_identity_kernel(g, k)
        # All of Eq. 10's weight on level 0 (the level-0 head also outputs the lambdas).
        last: torch.nn.Conv2d = model.kernel_gens[0].rest[-1]
        with torch.no_grad():
            last.bias[k * k :] = torch.tensor([100.0] + [0.0] * (model.config.levels - 1), dtype=last.bias.dtype)
    else:
        set_identity_kernel(model.kernel_gen, k)


@pytest.mark.parametrize("name", NAMES)
def test_permutation_invariance(name: str) -> None:
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    batch = synthetic_batch(model, spp=5, height=12, width=10)
    with torch.no_grad():
        y = model(batch)
        yp = model(permute_samples(batch, seed=5))
    assert rel_diff(yp, y) <= 1e-5


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("layers", [1, 2, 3])
def test_centre_kernel_gives_pixel_mean_for_any_layer_count(name: str, layers: int) -> None:
    """With centre-only kernels both compositing rules collapse to the mean of the samples."""
    torch.manual_seed(0)
    model = build_model(name, "small", layers=layers).double().eval()
    identity_kernels(model)
    batch = synthetic_batch(model, spp=3, height=9, width=7, dtype=torch.float64)
    with torch.no_grad():
        y = model(batch)
    # eps = 1e-6 in the occupancy normalisation bounds the agreement.
    assert rel_diff(y, batch["radiance"].mean(dim=1)) <= 1e-5


def test_partition_sums_and_occupancy() -> None:
    """Eq. 2 / Appendix A: layer weights sum to 1 per pixel, n_0 = 1, n_j = sum_{k>=j} w_k."""
    torch.manual_seed(0)
    model = build_model("layer", "small", layers=3).double().eval()
    batch = synthetic_batch(model, spp=4, height=6, width=5, dtype=torch.float64)
    with torch.no_grad():
        f, rad = model.features(batch)
        e = model.reducer(f)
        ctx = model.unet(e.mean(dim=1))
        l_rad, l_w, l_n, l_emb = model.partition(e, ctx, rad)
    assert torch.allclose(l_w.sum(dim=1), torch.ones_like(l_w[:, 0]), atol=1e-12)
    assert torch.allclose(l_n[:, 0], torch.ones_like(l_n[:, 0]), atol=1e-12)
    assert torch.allclose(l_n[:, 1], l_w[:, 1] + l_w[:, 2], atol=1e-12)
    assert torch.allclose(l_n[:, 2], l_w[:, 2], atol=1e-12)
    # The layers' radiance adds up to the pixel mean: partitioning loses no energy.
    assert torch.allclose(l_rad.sum(dim=1), rad.mean(dim=1), rtol=1e-12)
    assert l_emb.shape == (1, 3, model.config.embed_width, 6, 5)


def _composite_reference(logits, l_rad, l_w, l_n, weighted: bool, eps: float) -> torch.Tensor:
    """Eq. 3-6 written out with the unfold/fold splat reference and one global max."""
    wts = torch.exp(logits - logits.max())
    filt = []
    for j in range(logits.shape[1]):
        vals = torch.cat([l_rad[:, j], l_w[:, j], l_n[:, j]], dim=1).unsqueeze(1)
        num, _ = splat_reference(vals, wts[:, j : j + 1])
        filt.append(num)
    if weighted:  # Eq. 6
        return sum(f[:, :3] for f in filt) / (sum(f[:, 3:4] for f in filt) + eps)
    rad_hat = [f[:, :3] / (f[:, 4:5] + eps) for f in filt]  # Eq. 4
    alpha = [f[:, 3:4] / (f[:, 4:5] + eps) for f in filt]
    out = rad_hat[0]
    for lyr in range(1, len(filt)):  # Eq. 5
        t = torch.ones_like(alpha[0])
        for j in range(lyr):
            t = t * (1 - alpha[j])
        out = out + rad_hat[lyr] * t
    return out


@pytest.mark.parametrize("compositing", ["alpha", "weighted"])
def test_filter_matches_equations(compositing: str) -> None:
    torch.manual_seed(0)
    model = build_model("layer", "small", layers=3, compositing=compositing).double()
    g = torch.Generator().manual_seed(1)
    b, nl, k, h, w = 2, 3, model.config.kernel_size, 7, 8
    logits = torch.randn(b, nl, k * k, h, w, generator=g, dtype=torch.float64)
    wl = torch.softmax(torch.randn(b, 4, nl, h, w, generator=g, dtype=torch.float64), dim=2) / 4
    rad = torch.rand(b, 4, 3, h, w, generator=g, dtype=torch.float64)
    l_rad = torch.einsum("bslhw,bschw->blchw", wl, rad)
    l_w = wl.sum(1).unsqueeze(2)
    l_n = l_w.flip(1).cumsum(1).flip(1)
    got = model._filter(logits, l_rad, l_w, l_n)
    want = _composite_reference(logits, l_rad, l_w, l_n, compositing == "weighted", model.config.eps)
    assert rel_diff(got, want) <= 1e-4  # eps interacts with the different max shifts
    # With eps -> 0 the two agree to rounding.
    model.config.eps = 0.0
    got = model._filter(logits, l_rad, l_w, l_n)
    want = _composite_reference(logits, l_rad, l_w, l_n, compositing == "weighted", 0.0)
    assert rel_diff(got, want) <= 1e-10


def test_optimized_uses_three_levels_and_small_kernels() -> None:
    model = build_model("layer_optimized", "paper")
    assert model.config.kernel_size == 5 and model.config.levels == 3
    assert len(model.kernel_gens) == 3
    assert model.kernel_gens[0].out_channels == 25 + 3 and model.kernel_gens[1].out_channels == 25
    assert model.kernel_gens[1].rest[0].in_channels == 32  # kernel generator reduced to 32 (Sec. 6)
    small = build_model("layer_optimized", "small")
    batch = synthetic_batch(small, spp=2, height=11, width=9)
    small(batch).square().mean().backward()
    for g in small.kernel_gens:  # every level reaches the output
        assert g.first.weight.grad is not None and g.first.weight.grad.abs().sum() > 0


def test_paper_sizes() -> None:
    model = build_model("layer", "paper")
    cfg = model.config
    assert (cfg.embed_width, cfg.context_width, cfg.kernel_size, cfg.layers) == (32, 128, 17, 2)
    assert model.input_features == 20  # 20 floats per sample, as in the paper
    assert isinstance(model.partitioner, FCStack) and model.partitioner.out_channels == 2
    assert model.kernel_gen.out_channels == 289
