"""Layer-embedding denoiser: partitioning (Eq. 2), compositing (Eq. 3-6), invariance, any L."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

import mcdenoise.models.layer as layer_module
import mcdenoise.ops.composite as composite_module

from mcdenoise.models.blocks import FCStack
from mcdenoise.models.registry import build_model, synthetic_batch
from mcdenoise.ops.gather import gather_reference
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
@pytest.mark.parametrize("passes", [1, 2])
def test_permutation_invariance(name: str, passes: int) -> None:
    torch.manual_seed(0)
    model = build_model(name, "small", passes=passes).eval()
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
    assert rel_diff(y, batch["radiance"].mean(dim=1)) <= 1e-10


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


def _composite_reference(logits, l_rad, l_w, l_n, weighted: bool) -> torch.Tensor:
    """Eq. 3-6 written out with the unfold/fold splat reference, no max shift and no eps
    (exact in float64 for logits up to a few hundred)."""
    wts = torch.exp(logits)
    filt = []
    for j in range(logits.shape[1]):
        vals = torch.cat([l_rad[:, j], l_w[:, j], l_n[:, j]], dim=1).unsqueeze(1)
        num, _ = splat_reference(vals, wts[:, j : j + 1])
        filt.append(num)
    if weighted:  # Eq. 6
        return sum(f[:, :3] for f in filt) / sum(f[:, 3:4] for f in filt)
    rad_hat = [f[:, :3] / f[:, 4:5] for f in filt]  # Eq. 4
    alpha = [f[:, 3:4] / f[:, 4:5] for f in filt]
    out = rad_hat[0]
    for lyr in range(1, len(filt)):  # Eq. 5
        t = torch.ones_like(alpha[0])
        for j in range(lyr):
            t = t * (1 - alpha[j])
        out = out + rad_hat[lyr] * t
    return out


def _layer_sums(b: int, nl: int, h: int, w: int, dtype: torch.dtype, seed: int = 1):
    """Random per-layer sums as Eq. 2 makes them: l_rad (B, L, 3, h, w), l_w, l_n (B, L, 1, h, w)."""
    g = torch.Generator().manual_seed(seed)
    wl = torch.softmax(torch.randn(b, 4, nl, h, w, generator=g, dtype=torch.float64), dim=2) / 4
    rad = torch.rand(b, 4, 3, h, w, generator=g, dtype=torch.float64)
    l_rad = torch.einsum("bslhw,bschw->blchw", wl, rad)
    l_w = wl.sum(1).unsqueeze(2)
    l_n = l_w.flip(1).cumsum(1).flip(1)
    return l_rad.to(dtype), l_w.to(dtype), l_n.to(dtype)


@pytest.mark.parametrize("compositing", ["alpha", "weighted"])
def test_filter_matches_equations(compositing: str) -> None:
    """Catches: any deviation of the splat + compositing code from Eq. 3-6 (float64, random
    kernels); the max shift must cancel to rounding."""
    torch.manual_seed(0)
    model = build_model("layer", "small", layers=3, compositing=compositing).double()
    g = torch.Generator().manual_seed(1)
    b, nl, k, h, w = 2, 3, model.config.kernel_size, 7, 8
    logits = torch.randn(b, nl, k * k, h, w, generator=g, dtype=torch.float64)
    l_rad, l_w, l_n = _layer_sums(b, nl, h, w, torch.float64)
    got = model._filter(logits, l_rad, l_w, l_n)
    want = _composite_reference(logits, l_rad, l_w, l_n, compositing == "weighted")
    assert rel_diff(got, want) <= 1e-10


def neighbourhood_shift_exp(logits: torch.Tensor, kernel_size: int, *args, **kwargs) -> torch.Tensor:
    """A legal but adversarial per-destination shift: every tap landing on ``u`` is shifted by the
    max of *all* logits of all sources within K x K of ``u`` (the shift ``per_destination_exp``
    used before issue 8). It is constant per destination, so exact compositing must not notice it;
    it is larger than the landing max, so it scales the sums of a dim pixel next to a peaked one
    by exp(-gap)."""
    b, s, kk, h, w = logits.shape
    k, r = kernel_size, kernel_size // 2
    with torch.no_grad():
        m = logits.amax(dim=(1, 2)).unsqueeze(1)
        c = F.max_pool2d(m, k, stride=1, padding=r)
        shift = F.unfold(F.pad(c, (r, r, r, r), mode="replicate"), k).reshape(b, 1, kk, h, w)
    return torch.exp(logits - shift)


@pytest.mark.parametrize("shift", ["library", "neighbourhood"])
@pytest.mark.parametrize("compositing", ["alpha", "weighted"])
@pytest.mark.parametrize("peak", [20.0, 30.0])
def test_peaked_kernel_does_not_darken_its_neighbours(
    compositing: str, peak: float, shift: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 8 bug 2: an eps (1e-6) added to the filtered occupancy after a per-destination max
    shift. One pixel whose kernel logit peaks at 20 (30) sets the shift of every pixel within a
    kernel radius, whose sums then carry a factor exp(-20) (exp(-30)); the eps swamped them and
    those pixels came out at 8.5% (4e-6) of the exact value. Compared in float32, small preset,
    against the same equations in float64 with neither shift nor eps, under the library's shift
    and under the neighbourhood-max shift (compositing must be exact under any per-destination
    shift, not only under the one ``ops.kernels`` happens to use)."""
    if shift == "neighbourhood":
        monkeypatch.setattr(composite_module, "per_destination_exp", neighbourhood_shift_exp)
    torch.manual_seed(0)
    model = build_model("layer", "small", compositing=compositing)
    b, nl, k, h, w = 1, model.config.layers, model.config.kernel_size, 15, 16
    g = torch.Generator().manual_seed(2)
    logits = torch.randn(b, nl, k * k, h, w, generator=g, dtype=torch.float64)
    logits[:, :, (k * k) // 2, 7, 8] = peak  # one sharply peaked kernel in the middle
    l_rad, l_w, l_n = _layer_sums(b, nl, h, w, torch.float64)
    want = _composite_reference(logits, l_rad, l_w, l_n, compositing == "weighted")
    with torch.no_grad():
        got = model._filter(logits.float(), l_rad.float(), l_w.float(), l_n.float())
    assert torch.isfinite(got).all()
    # Pixel-wise: the bug left a band of pixels at a few percent of the truth.
    assert ((got.double() / want) - 1).abs().max() <= 1e-4


@pytest.mark.parametrize("compositing", ["alpha", "weighted"])
def test_layer_with_no_weight_under_the_largest_logit_still_counts(compositing: str) -> None:
    """Catches: a filtered denominator that underflows to 0 while the exact one is positive.
    Where one layer's partition weight is exactly 0 (a softmax over layers that underflowed, as
    with peaked partitioner logits) but its kernel logits are 100 above the other layer's, a
    shift taken from the logits alone underflows every tap that carries weight; the sums are
    shifted by the max of logit + log(weight) instead."""
    torch.manual_seed(0)
    model = build_model("layer", "small", compositing=compositing).double()
    b, nl, k, h, w = 1, 2, model.config.kernel_size, 9, 10
    g = torch.Generator().manual_seed(4)
    logits = torch.randn(b, nl, k * k, h, w, generator=g, dtype=torch.float64)
    l_rad, l_w, l_n = _layer_sums(b, nl, h, w, torch.float64)
    # Layer 1 is empty at every pixel, yet its kernels' logits dwarf layer 0's.
    l_w = torch.cat([torch.ones_like(l_w[:, :1]), torch.zeros_like(l_w[:, 1:])], dim=1)
    l_n = l_w.flip(1).cumsum(1).flip(1)
    l_rad = torch.cat([l_rad[:, :1] / l_rad[:, :1].amax(), torch.zeros_like(l_rad[:, 1:])], dim=1)
    logits[:, 1] += 800.0  # exp(-800) underflows even float64
    logits[:, 0, :, 4, 5] += 40.0  # and one peaked layer-0 kernel
    want = _composite_reference(logits[:, :1], l_rad[:, :1], l_w[:, :1], l_n[:, :1], compositing == "weighted")
    got = model._filter(logits, l_rad, l_w, l_n)
    assert torch.isfinite(got).all()
    assert rel_diff(got, want) <= 1e-10


def test_compositing_gradients_are_finite_where_nothing_lands() -> None:
    """Catches: ``where(den > 0, num / den, 0)`` written without guarding the denominator, which
    gives NaN gradients (0 * inf) at pixels whose sums are exactly 0."""
    torch.manual_seed(0)
    model = build_model("layer", "small").double()
    b, nl, k, h, w = 1, 2, model.config.kernel_size, 9, 10
    logits = torch.zeros(b, nl, k * k, h, w, dtype=torch.float64, requires_grad=True)
    l_rad, l_w, l_n = _layer_sums(b, nl, h, w, torch.float64)
    l_w = torch.cat([torch.ones_like(l_w[:, :1]), torch.zeros_like(l_w[:, 1:])], dim=1)
    l_n = l_w.flip(1).cumsum(1).flip(1)
    l_rad = l_rad * l_w
    l_rad.requires_grad_(True)
    model._filter(logits, l_rad, l_w, l_n).sum().backward()
    assert torch.isfinite(logits.grad).all() and torch.isfinite(l_rad.grad).all()


@pytest.mark.parametrize("compositing", ["alpha", "weighted"])
def test_compositing_gradients_survive_a_nearly_empty_layer(compositing: str) -> None:
    """Catches: folding each layer's sums by the live normalising sum. Its backward divides the
    folded value (an HDR mean, ~1e3) by the sum again; where a saturated partitioner leaves a layer
    1e-36 of the weight that overflows float32 and meets a zero kernel weight: 0 * inf = NaN
    (campaign 13's layer_optimized on a GPU had NaN gradients from step 10 on). float32 gradients
    must be finite and match float64's on the same inputs (measured 4e-6 apart; bound 1e-3)."""
    torch.manual_seed(0)
    model = build_model("layer", "small", compositing=compositing)
    b, nl, k, h, w = 1, 2, model.config.kernel_size, 9, 10
    g = torch.Generator().manual_seed(6)
    logits = torch.randn(b, nl, k * k, h, w, generator=g, dtype=torch.float64)
    l_rad, l_w, _ = _layer_sums(b, nl, h, w, torch.float64)
    share = torch.ones(1, nl, 1, h, w, dtype=torch.float64)
    share[:, 1, :, :, ::2] = 1e-36  # layer 1 nearly empty in every other column
    l_rad, l_w = l_rad * share * 1e3, l_w * share
    l_n = l_w.flip(1).cumsum(1).flip(1)
    sums = [t.float().double() for t in (l_rad, l_w, l_n)]  # the same inputs in both precisions

    def grads(dtype: torch.dtype) -> list[torch.Tensor]:
        ins = [t.to(dtype).requires_grad_(True) for t in sums]
        lg = logits.to(dtype).clone().requires_grad_(True)
        out = model.to(dtype)._filter(lg, *ins)
        (out * torch.linspace(0.5, 1.5, out.numel(), dtype=dtype).reshape(out.shape)).sum().backward()
        # Eq. 6 never reads l_n: no gradient there.
        return [t.grad.double() for t in ins + [lg] if t.grad is not None]

    for got, want in zip(grads(torch.float32), grads(torch.float64)):
        assert torch.isfinite(got).all()
        assert rel_diff(got, want) <= 1e-3


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


# -- Tests that structural mutations must fail (issue 8 item 13) -------------------------------

#: Parameter counts of the presets, pinned as literals: a count recomputed from the same code
#: cannot notice a U-Net one level shallower, a missing skip concatenation or a narrower head.
PAPER_COUNTS = {
    ("layer", "paper"): 18_001_235,
    ("layer_weighted", "paper"): 18_001_235,
    ("layer_optimized", "paper"): 17_329_216,
    ("layer_optimized", "paper_timed"): 1_024_976,
    ("layer", "small"): 31_995,
    ("layer", "medium"): 987_731,
    ("layer_weighted", "small"): 31_995,
    ("layer_optimized", "small"): 35_640,
}


@pytest.mark.parametrize("name,preset", sorted(PAPER_COUNTS))
def test_parameter_counts_are_pinned(name: str, preset: str) -> None:
    """Catches: the layer U-Net one level shallower (or deeper), skip channels dropped from the
    decoder's input, any change of a width in a preset (Appendix B, Sec. 6, our ``paper_timed``)."""
    model = build_model(name, preset)
    assert sum(p.numel() for p in model.parameters()) == PAPER_COUNTS[(name, preset)]
    if preset not in ("small", "medium"):  # ours: 2 and 4 levels
        assert model.unet.levels == 5  # Fig. 3 has five pooling levels (32x downsampling)


@pytest.mark.parametrize("name", NAMES)
def test_every_parameter_element_gets_a_gradient(name: str) -> None:
    """Catches (each leaves some weights with an exactly zero or missing gradient): U-Net skip
    connections zeroed (decoder weights reading the skip channels), a U-Net level skipped in the
    forward pass (its blocks get no gradient), the kernel generator ignoring the layer embedding
    (its first layer's weights), the partitioner ignoring the context (its context projection),
    any head or level of the hierarchy that does not reach the output."""
    torch.manual_seed(0)
    model = build_model(name, "small")
    batch = synthetic_batch(model, spp=3, height=16, width=16)
    out = model(batch)
    w = torch.rand(out.shape, generator=torch.Generator().manual_seed(1))
    (out * w).sum().backward()
    for pname, p in model.named_parameters():
        assert p.grad is not None, f"{name}: {pname} receives no gradient"
        assert torch.isfinite(p.grad).all(), f"{name}: {pname} has a non-finite gradient"
        zero = int((p.grad == 0).sum())
        assert zero == 0, f"{name}: {zero} of {p.numel()} elements of {pname} get an exactly zero gradient"


def _groups(model) -> list[str]:
    return list(model.config.channels) + ["scene_features"]


@pytest.mark.parametrize("name", NAMES)
def test_output_depends_on_every_input_group(name: str) -> None:
    """Catches: an input channel group (radiance, specular, albedo, normal, depth, roughness,
    lens, time, sub-pixel position, scene features for the circle of confusion) read but not used,
    e.g. zeroed or dropped from the features."""
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    batch = synthetic_batch(model, spp=2, height=8, width=8)
    with torch.no_grad():
        y = model(batch)
        for group in _groups(model):
            changed = dict(batch)
            g = torch.Generator().manual_seed(7)
            changed[group] = batch[group] + 0.5 * torch.rand(batch[group].shape, generator=g)
            d = rel_diff(model(changed), y)
            assert d > 1e-5, f"{name}: output does not depend on {group} (rel. change {d:.2g})"


@pytest.mark.parametrize("name", NAMES)
def test_hdr_radiance_is_log_compressed(name: str) -> None:
    """Catches: radiance (or any HDR channel) fed to the networks without log compression. A
    firefly of 1e5 must enter the sample reducer as log(1 + 1e5) ~ 11.5, not as 1e5 (Sec. 3)."""
    model = build_model(name, "small")
    batch = synthetic_batch(model, spp=2, height=6, width=6)
    batch["radiance"][0, 0, :, 2, 3] = 1e5
    batch["specular"][0, 1, :, 4, 1] = 1e5
    f, rad = model.features(batch)
    assert rad[0, 0, 0, 2, 3] == 1e5  # the radiance that is filtered stays linear
    assert f.abs().max() <= torch.log1p(torch.tensor(1e5)) + 1e-4
    assert torch.allclose(f[:, :, :3], torch.log1p(batch["radiance"]))


def test_paper_timed_unet_fits_the_papers_timing() -> None:
    """Catches: a ``paper_timed`` U-Net that no longer fits Table 3's 18.8 ms at 1920x1080 on an
    RTX 2080 Ti, i.e. more than 136 kFLOP per pixel (15 TFLOP/s x 18.8 ms / 2.07 Mpixel; see
    docs/models/layer.md), and the unverified ``paper`` U-Net being mistaken for one that fits."""

    def unet_flop_per_pixel(model) -> float:
        total = 0

        def hook(mod: torch.nn.Conv2d, inp, out) -> None:
            nonlocal total
            total += 2 * out.numel() * mod.in_channels * mod.kernel_size[0] * mod.kernel_size[1] // mod.groups

        hooks = [m.register_forward_hook(hook) for m in model.unet.modules() if isinstance(m, torch.nn.Conv2d)]
        with torch.no_grad():
            model.unet(torch.zeros(1, model.config.embed_width, 64, 64))
        for h in hooks:
            h.remove()
        return total / (64 * 64)

    budget = 15e12 * 18.8e-3 / (1920 * 1080)
    timed = unet_flop_per_pixel(build_model("layer_optimized", "paper_timed"))
    assert 0.5 * budget < timed <= budget, timed
    assert unet_flop_per_pixel(build_model("layer_optimized", "paper")) > 4 * budget


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("passes", [1, 2])
def test_row_banded_inference_matches_whole_image(name: str, passes: int, monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches: a band seam in the memory-bounded inference path (issue 8 item 12): kernels
    splatting across a band boundary lost or counted twice, a shift that differs between the
    two passes, the partition of one band reading another band's context, Eq. 10 weights
    collected from the wrong pass. Bands of a few rows (the budget shrunk) against one band.
    With two runs (``passes``), also a banded context that reads the kept embeddings of the
    samples as given instead of the moved ones."""
    torch.manual_seed(0)
    model = build_model(name, "small", passes=passes).double().eval()
    batch = synthetic_batch(model, spp=3, height=21, width=10, dtype=torch.float64)
    with torch.no_grad():
        whole = model(batch)
        monkeypatch.setattr(layer_module, "_BAND_ELEMS", 1)  # one row per band everywhere
        banded = model(batch)
        b, s, _, h, w = batch["radiance"].shape
        kk = model.config.kernel_size**2
        monkeypatch.setattr(layer_module, "_BAND_ELEMS", 4 * b * model.config.layers * (kk + 3) * w)
        four_rows = model(batch)
        monkeypatch.setattr(layer_module, "_KEEP_BYTES", 0)  # reducer recomputed in the second pass
        recomputed = model(batch)
    assert rel_diff(banded, whole) <= 1e-12
    assert rel_diff(four_rows, whole) <= 1e-12
    assert rel_diff(recomputed, whole) <= 1e-12


def test_banded_inference_keeps_the_reducer_output(monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches: the second banded pass recomputing the features and the reducer although their
    output was kept (twice the per-sample cost once bands start: 32 spp at 256x256 cost 6-8x
    the 16-spp time)."""
    model = build_model("layer_optimized", "small").eval()
    batch = synthetic_batch(model, spp=2, height=12, width=6)
    calls = []
    model.reducer.register_forward_hook(lambda *a: calls.append(1))
    monkeypatch.setattr(layer_module, "_BAND_ELEMS", 1)
    with torch.no_grad():
        model(batch)
        kept = len(calls)
        monkeypatch.setattr(layer_module, "_KEEP_BYTES", 0)
        calls.clear()
        model(batch)
    assert kept == 12 and len(calls) == 24, (kept, len(calls))


@pytest.mark.parametrize("compositing", ["alpha", "weighted"])
def test_compositing_gradcheck(compositing: str) -> None:
    """Catches: a wrong gradient through the compositing (the log-weight folding, the in-place
    exponentiation, the guarded divisions), float64 finite differences on a 3x3-kernel layer."""
    model = build_model("layer", "small", kernel_size=3, compositing=compositing).double()
    b, nl, h, w = 1, 2, 5, 4
    g = torch.Generator().manual_seed(5)
    logits = torch.randn(b, nl, 9, h, w, generator=g, dtype=torch.float64, requires_grad=True)
    l_rad, l_w, l_n = _layer_sums(b, nl, h, w, torch.float64)
    l_rad.requires_grad_(True)
    l_w.requires_grad_(True)
    l_n.requires_grad_(True)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # ~1000 tiny forwards: OpenMP start-up would dominate on a busy machine
    try:
        assert torch.autograd.gradcheck(lambda *x: model._filter(*x), (logits, l_rad, l_w, l_n))
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("factor", [1.0, 3.0])
@pytest.mark.parametrize("name", NAMES)
def test_gather_form_keeps_a_constant_image_constant(name: str, factor: float) -> None:
    """Catches, for ``splat=False`` (kernels applied as gathers): one shift shared by both layers
    underflowing the layer with the lower logits, or a neighbour with zero partition weight under
    a pixel's largest logit underflowing the rest (0 instead of 1 once parameters are x3)."""
    from test_model_invariants import _scaled, constant_batch

    torch.manual_seed(0)
    model = _scaled(build_model(name, "small", splat=False).eval(), factor)
    with torch.no_grad():
        out = model(constant_batch(model))
    assert (out - 1).abs().max() < 1e-3


@pytest.mark.parametrize("compositing", ["alpha", "weighted"])
def test_gather_form_matches_equations(compositing: str) -> None:
    """Catches: the gather form of Eq. 3-6 deviating from the equations (float64, no shift)."""
    model = build_model("layer", "small", layers=3, compositing=compositing, splat=False).double()
    b, nl, k, h, w = 1, 3, model.config.kernel_size, 7, 8
    g = torch.Generator().manual_seed(6)
    logits = torch.randn(b, nl, k * k, h, w, generator=g, dtype=torch.float64)
    l_rad, l_w, l_n = _layer_sums(b, nl, h, w, torch.float64)
    filt = []
    for j in range(nl):
        vals = torch.cat([l_rad[:, j], l_w[:, j], l_n[:, j]], dim=1)
        filt.append(gather_reference(vals, torch.exp(logits[:, j])))
    if compositing == "weighted":
        want = sum(f[:, :3] for f in filt) / sum(f[:, 3:4] for f in filt)
    else:
        want, t = torch.zeros_like(filt[0][:, :3]), torch.ones_like(filt[0][:, 3:4])
        for f in filt:
            want = want + t * f[:, :3] / f[:, 4:5]
            t = t * (1 - f[:, 3:4] / f[:, 4:5])
    assert rel_diff(model._filter(logits, l_rad, l_w, l_n), want) <= 1e-10


def test_sample_weighted_sum_equals_einsum_and_inference_equals_training_path() -> None:
    """Catches: the inference-only per-layer sample sum (a loop of multiply-adds replacing
    einsum) summing the wrong sample or layer, or the no_grad forward of a layer model drifting
    from the autograd (einsum) forward; float64, non-contiguous inputs as the banded path has."""
    from mcdenoise.models.layer import _sample_weighted_sum

    g = torch.Generator().manual_seed(4)
    w = torch.rand(2, 5, 3, 9, 7, generator=g, dtype=torch.float64)
    x = torch.randn(2, 5, 4, 11, 7, generator=g, dtype=torch.float64)[..., 1:10, :]
    torch.testing.assert_close(_sample_weighted_sum(w, x), torch.einsum("bslhw,bschw->blchw", w, x), rtol=1e-12, atol=1e-12)
    torch.manual_seed(0)
    model = build_model("layer_optimized", "small").double().eval()
    batch = synthetic_batch(model, spp=3, height=9, width=8, dtype=torch.float64)
    with torch.no_grad():
        fast = model(batch)
    ref = model(batch).detach()
    assert rel_diff(fast, ref) <= 1e-12


@pytest.mark.parametrize("name", NAMES)
def test_second_pass_reads_its_context_from_samples_moved_to_the_first_output(name: str) -> None:
    """Catches a second run whose context reads the samples as given (it would repeat the first
    run), moved samples that lose their spread or miss the first output, and a second run whose
    kernels filter the moved samples instead of the samples as given: it must equal the first
    run's network with its U-Net fed the moved samples' mean embedding, built by hand here."""
    torch.manual_seed(0)
    one = build_model(name, "small", consistency=4.0, autoexposure=0.18).double().eval()
    two = build_model(name, "small", consistency=4.0, autoexposure=0.18, passes=2).double().eval()
    two.load_state_dict(one.state_dict())
    batch = synthetic_batch(one, spp=4, height=12, width=10, dtype=torch.float64)
    with torch.no_grad():
        first = one(batch)
        got = two(batch)
        moved = {**batch, "radiance": layer_module.shifted_samples(batch["radiance"], first)}
        s = one.exposure_of(batch)
        seen = []
        orig = one._unet

        def unet_of_moved(mean: torch.Tensor):  # the U-Net's input in the one-pass model, replaced
            seen.append(mean)
            e = one.reducer(one.features(layer_module.scale_batch(dict(moved), s))[0])
            return orig(e.mean(dim=1))

        one._unet = unet_of_moved
        want = one(batch)
    assert seen and rel_diff(got, want) <= 1e-10
    assert rel_diff(got, first) > 1e-4  # the second run changes the output
    torch.testing.assert_close(moved["radiance"].mean(dim=1), first)


def test_passes_must_be_at_least_one() -> None:
    with pytest.raises(ValueError, match="passes must be >= 1"):
        build_model("layer", "small", passes=0)
