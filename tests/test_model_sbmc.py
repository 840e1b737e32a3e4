"""SBMC and its Table 2 ablations: the properties the paper relies on."""

from __future__ import annotations

import pytest
import torch

from mcdenoise.models.blocks import FCStack, UNet
from mcdenoise.ops.kernels import per_destination_exp
from mcdenoise.models.registry import build_model, synthetic_batch
from mcdenoise.ops.splat import normalize_splat, splat_reference

INVARIANT = ("sbmc", "pixel_splat", "pixel_gather")
ALL = INVARIANT + ("sbmc_gather",)


def permute_samples(batch: dict[str, torch.Tensor], seed: int) -> dict[str, torch.Tensor]:
    """Shuffle the samples of every pixel independently (same permutation for all channels)."""
    x0 = next(v for k, v in batch.items() if k != "scene_features")
    b, s, _, h, w = x0.shape
    g = torch.Generator().manual_seed(seed)
    perm = torch.argsort(torch.rand(b, s, 1, h, w, generator=g), dim=1)
    out = {}
    for k, v in batch.items():
        out[k] = v if k == "scene_features" else torch.gather(v, 1, perm.expand(-1, -1, v.shape[2], -1, -1))
    return out


def rel_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(((a - b).abs().max() / b.abs().max()).detach())


def set_identity_kernel(fc: FCStack, k: int) -> None:
    """Make the kernel head output all weight on the centre tap, whatever its input."""
    last = fc.rest[-1] if len(fc.rest) else fc.first
    with torch.no_grad():
        last.weight.zero_()
        last.bias.fill_(-1e4)
        last.bias[(k * k) // 2] = 0.0


@pytest.mark.parametrize("name", INVARIANT)
def test_permutation_invariance(name: str) -> None:
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    batch = synthetic_batch(model, spp=5, height=12, width=10)
    with torch.no_grad():
        y = model(batch)
        yp = model(permute_samples(batch, seed=3))
    assert rel_diff(yp, y) <= 1e-5


def test_gather_ablation_is_not_permutation_invariant() -> None:
    """Table 2 "Gather" couples sample index s across pixels (Fig. 5), so shuffling changes it."""
    torch.manual_seed(0)
    model = build_model("sbmc_gather", "small").eval()
    batch = synthetic_batch(model, spp=5, height=12, width=10)
    with torch.no_grad():
        d = rel_diff(model(permute_samples(batch, seed=3)), model(batch))
    assert d > 1e-4


@pytest.mark.parametrize("name", ALL)
def test_centre_kernel_gives_pixel_mean(name: str) -> None:
    """All kernel weight on the centre tap: splat and gather both reduce to the mean of samples."""
    torch.manual_seed(0)
    model = build_model(name, "small").double().eval()
    set_identity_kernel(model.kernel, model.config.kernel_size)
    for spp in (1, 3, 8):
        batch = synthetic_batch(model, spp=spp, height=7, width=9, dtype=torch.float64)
        with torch.no_grad():
            y = model(batch)
        assert rel_diff(y, batch["radiance"].mean(dim=1)) <= 1e-7


@pytest.mark.parametrize("name", ALL)
def test_any_spp_and_odd_size(name: str) -> None:
    model = build_model(name, "small").eval()
    for spp in (1, 3, 8):
        batch = synthetic_batch(model, batch=2, spp=spp, height=9, width=13)
        with torch.no_grad():
            y = model(batch)
        assert y.shape == (2, 3, 9, 13) and torch.isfinite(y).all()


def test_output_is_a_convex_combination_of_samples() -> None:
    """Eq. 1 normalises per output pixel, so every output lies inside the range of the input samples."""
    torch.manual_seed(0)
    model = build_model("sbmc", "small").eval()
    batch = synthetic_batch(model, spp=4, height=12, width=12)
    with torch.no_grad():
        y = model(batch)
    rad = batch["radiance"]
    assert float(y.min()) >= float(rad.min()) - 1e-5
    assert float(y.max()) <= float(rad.max()) * (1 + 1e-5)


def test_per_destination_exp_is_exact_and_stable() -> None:
    """The per-destination max shift leaves Eq. 1 unchanged (float64) and survives huge logits."""
    g = torch.Generator().manual_seed(0)
    b, s, k, h, w = 2, 3, 5, 8, 9
    logits = torch.randn(b, s, k * k, h, w, generator=g, dtype=torch.float64) * 3
    values = torch.rand(b, s, 3, h, w, generator=g, dtype=torch.float64)
    ref_num, ref_w = splat_reference(values, torch.exp(logits))
    ref = normalize_splat(ref_num, ref_w, 0.0)
    num, wsum = splat_reference(values, per_destination_exp(logits, k))
    assert rel_diff(normalize_splat(num, wsum, 0.0), ref) <= 1e-12
    # A region 2000 above the rest: plain exp overflows, a global max would zero the other side.
    big = logits.clone()
    big[..., :, :3] += 2000.0
    num, wsum = splat_reference(values, per_destination_exp(big, k))
    out = normalize_splat(num, wsum, 0.0)
    assert torch.isfinite(out).all()
    # Far from the bright region (columns >= 3 + 2r) only normal logits land: same result as before.
    far = slice(3 + 2 * (k // 2), None)
    assert rel_diff(out[..., far], ref[..., far]) <= 1e-12


def test_paper_preset_sizes() -> None:
    """Sec. 3.2/3.5: 128-wide embeddings, 3 FC layers, 3 U-Net steps, 21x21 kernels."""
    model = build_model("sbmc", "paper")
    cfg = model.config
    assert (cfg.embed_width, cfg.fc_layers, cfg.steps, cfg.kernel_size) == (128, 3, 3, 21)
    assert len(model.unets) == 3 and all(isinstance(u, UNet) for u in model.unets)
    assert model.kernel.out_channels == 441
    pix = build_model("pixel_gather", "paper")
    # Pixel statistics (mean and variance) double the per-sample feature width.
    assert pix.embed0.in_channels - 5 == 2 * (model.embed0.in_channels - 5)


def test_fcstack_context_equals_concatenation() -> None:
    """The split first layer is FC(cat(x, context)) without copying the context per sample."""
    g = torch.Generator().manual_seed(0)
    fc = FCStack(4, [6, 5], context_channels=3).double()
    x = torch.randn(2, 3, 4, 5, 6, generator=g, dtype=torch.float64)
    ctx = torch.randn(2, 3, 5, 6, generator=g, dtype=torch.float64)
    got = fc(x, ctx)
    w = torch.cat([fc.first.weight, fc.first_ctx.weight], dim=1)  # type: ignore[union-attr]
    cat = torch.cat([x, ctx.unsqueeze(1).expand(-1, 3, -1, -1, -1)], dim=2).reshape(6, 7, 5, 6)
    h = torch.nn.functional.leaky_relu(torch.nn.functional.conv2d(cat, w, fc.first.bias), 0.01)
    want = torch.nn.functional.leaky_relu(fc.rest[0](h), 0.01).reshape(2, 3, 5, 5, 6)
    assert rel_diff(got, want) <= 1e-12


def test_unet_any_size_and_decoder_levels() -> None:
    net = UNet(3, 4, ((4,), (8,)), (8,), ((8,), (4,)))
    x = torch.randn(1, 3, 9, 13)
    y, dec = net(x, return_decoder=True)
    assert y.shape == (1, 4, 9, 13)
    assert [tuple(d.shape[-2:]) for d in dec] == [(5, 7), (9, 13)]


def test_chunked_kernel_generation_matches() -> None:
    """A tiny kernel budget forces per-chunk kernel generation (two passes): same output."""
    torch.manual_seed(0)
    model = build_model("sbmc", "small").double().eval()
    batch = synthetic_batch(model, spp=5, height=8, width=9, dtype=torch.float64)
    with torch.no_grad():
        full = model(batch)
        model.config.kernel_budget_mb = 0  # -> one sample per chunk
        chunked = model(batch)
    assert rel_diff(chunked, full) <= 1e-12


def test_gradcheck_normalised_splat_through_shifted_exp() -> None:
    """The detached per-destination shift cancels in Eq. 1, so gradients w.r.t. logits are exact."""
    g = torch.Generator().manual_seed(2)
    k = 3
    logits = torch.randn(1, 2, k * k, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)
    values = torch.rand(1, 2, 2, 4, 5, generator=g, dtype=torch.float64, requires_grad=True)

    def f(lg: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        num, wsum = splat_reference(v, per_destination_exp(lg, k))
        return normalize_splat(num, wsum, 0.0)

    assert torch.autograd.gradcheck(f, (logits, values), eps=1e-6, atol=1e-8, rtol=1e-6)


# --- Issue 8: banded inference, paper sizes, and tests that catch mutations of the model ---------

#: Paper-preset parameter counts, as literals: a count computed from the same code would follow
#: any change to it. 3 U-Nets of 3 convs per level (authors' code), 3 FC stacks of 128, 441 taps.
PAPER_PARAMS = {"sbmc": 34_908_345, "sbmc_gather": 34_908_345, "pixel_splat": 34_913_081, "pixel_gather": 34_913_081}
SMALL_PARAMS = {"sbmc": 88_889, "sbmc_gather": 88_889, "pixel_splat": 89_481, "pixel_gather": 89_481}


@pytest.mark.parametrize("name", ALL)
def test_paper_and_small_parameter_counts_are_pinned(name: str) -> None:
    """Catches: any change of architecture (a dropped U-Net conv, a kernel head built without its
    context input, a missing step) that the paper-size test above would not see."""
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    assert count(build_model(name, "paper")) == PAPER_PARAMS[name]
    assert count(build_model(name, "small")) == SMALL_PARAMS[name]


def test_paper_unet_has_three_convs_per_level() -> None:
    """Item 7: the authors' code runs 3 convolutions per U-Net level (ours had 2)."""
    unet = build_model("sbmc", "paper").unets[0]
    blocks = list(unet.enc) + [unet.bottleneck] + list(unet.dec)
    convs = [sum(isinstance(m, torch.nn.Conv2d) for m in blk) for blk in blocks]
    assert convs == [3] * 5
    assert [blk.out_channels for blk in blocks] == [128, 256, 512, 256, 128]


@pytest.mark.parametrize("name", ALL)
def test_training_path_equals_banded_inference(name: str) -> None:
    """Inference runs the per-sample networks and kernels one band of rows at a time; training runs
    them whole or a chunk of samples at a time. Catches: any of the three paths diverging (a wrong
    band offset, a shift that differs per band or chunk, a step or input dropped in one path)."""
    torch.manual_seed(0)
    model = build_model(name, "small").double().eval()
    batch = synthetic_batch(model, spp=3, height=11, width=9, dtype=torch.float64)
    with torch.enable_grad():
        whole = model(batch).detach()
        model.config.kernel_budget_mb = 0  # training path: one sample per chunk (splat variants)
        chunked = model(batch).detach()
    with torch.no_grad():
        banded = model(batch)  # budget 0: one row per band
        model.config.kernel_budget_mb = 1024
        one_band = model(batch)
    for got in (chunked, banded, one_band):
        assert rel_diff(got, whole) <= 1e-12


@pytest.mark.parametrize("name", ALL)
def test_every_parameter_receives_a_gradient(name: str) -> None:
    """Catches: a U-Net step that never runs (e.g. only the first of the steps), a kernel head whose
    context input is ignored or zeroed, any sub-network cut off from the output."""
    torch.manual_seed(0)
    model = build_model(name, "small").double().train()
    batch = synthetic_batch(model, spp=3, height=10, width=8, dtype=torch.float64)
    target = torch.rand(1, 3, 10, 8, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ((model(batch) - target).square().mean()).backward()
    dead = [n for n, p in model.named_parameters() if p.grad is None or float(p.grad.abs().sum()) == 0.0]
    assert not dead, f"{name}: no gradient reaches {dead}"


def _perturbed(batch: dict[str, torch.Tensor], key: str) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(7)
    out = dict(batch)
    out[key] = batch[key] + 0.5 * torch.rand(batch[key].shape, generator=g, dtype=batch[key].dtype) + 0.1
    return out


@pytest.mark.parametrize("name", ALL)
def test_output_depends_on_every_input_group_and_every_step(name: str) -> None:
    """Inference path (no gradients). Catches: scene features zeroed or dropped, any feature channel
    ignored, and a U-Net step skipped in the banded inference loop (perturbing that step's U-Net
    must change the output)."""
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    batch = synthetic_batch(model, spp=3, height=10, width=8)
    with torch.no_grad():
        y = model(batch)
        for key in list(model.config.channels) + ["scene_features"]:
            if key == "radiance":
                continue  # also what is filtered; its network input is tested below
            assert rel_diff(model(_perturbed(batch, key)), y) > 1e-6, f"{name}: output ignores {key}"
        for i, unet in enumerate(model.unets):
            saved = [p.clone() for p in unet.parameters()]
            for p in unet.parameters():
                p.add_(0.1 * torch.randn_like(p))
            changed = rel_diff(model(batch), y)
            for p, s in zip(unet.parameters(), saved):
                p.copy_(s)
            assert changed > 1e-6, f"{name}: U-Net step {i} does not affect the output"


@pytest.mark.parametrize("name", ALL)
def test_radiance_reaches_the_network_log_compressed(name: str) -> None:
    """Appendix A: the kernel predictor consumes log radiance (the splat acts on linear radiance).
    Catches: radiance (or its diffuse/specular split) fed to the network without compression."""
    model = build_model(name, "small")
    batch = synthetic_batch(model, spp=3, height=5, width=4)
    for key in ("radiance", "diffuse", "specular"):
        batch[key] = batch[key] * 1e4
    f, lin = model.features(batch)
    col = 0
    for key in model.config.channels:
        n = batch[key].shape[2]
        if key in ("radiance", "diffuse", "specular"):
            want = torch.log1p(batch[key])
            want = want if model.config.per_sample else want.mean(dim=1, keepdim=True)
            torch.testing.assert_close(f[:, :, col : col + n], want)
        col += n
    assert float(f.abs().max()) < 30.0  # log(1e4 * x) stays small; linear 1e4 would not
    assert rel_diff(lin.sum(1) if model.config.per_sample else lin[:, 0] * 3, batch["radiance"].sum(1)) <= 1e-6
