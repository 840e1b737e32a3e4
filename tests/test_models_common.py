"""Tests every registered model, none left out: shapes, any spp, odd sizes, backward, 2-step training."""

from __future__ import annotations

import math

import pytest
import torch

from mcdenoise.models.registry import list_models, build_model, synthetic_batch

#: The issue's list. A model missing from the registry fails here instead of going untested.
EXPECTED = {
    "kpcn", "dpcn", "kpcn_single", "layer_weighted", "sbmc", "sbmc_gather", "pixel_gather", "pixel_splat",
    "layer", "layer_optimized", "wskp", "wskp_mr",
}
ALL = sorted(e.name for e in list_models())


def test_registry_has_every_model_of_the_issue() -> None:
    missing = EXPECTED - set(ALL)
    assert not missing, f"models not registered: {sorted(missing)}"


@pytest.mark.parametrize("name", ALL)
def test_presets_build_and_paper_is_larger(name: str) -> None:
    small = build_model(name, "small")
    paper = build_model(name, "paper")
    n_small = sum(p.numel() for p in small.parameters())
    n_paper = sum(p.numel() for p in paper.parameters())
    assert 0 < n_small <= n_paper, (n_small, n_paper)
    assert small.input_kind in ("pixels", "samples")
    assert small.required_channels(), "a model must declare the channels it reads"


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("size", [(16, 16), (17, 23)])
def test_output_shape_any_spp_and_odd_size(name: str, size: tuple[int, int]) -> None:
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    h, w = size
    spps = (1, 3, 8) if model.input_kind == "samples" else (1,)
    for spp in spps:
        batch = synthetic_batch(model, batch=2, spp=spp, height=h, width=w)
        with torch.no_grad():
            out = model(batch)
        assert out.shape == (2, 3, h, w), (name, spp, out.shape)
        assert out.dtype == torch.float32
        assert torch.isfinite(out).all(), (name, spp)


@pytest.mark.parametrize("name", ALL)
def test_two_step_training_smoke(name: str) -> None:
    """Two Adam steps on tiny synthetic data: gradients reach the weights, loss stays finite."""
    torch.manual_seed(0)
    model = build_model(name, "small").train()
    g = torch.Generator().manual_seed(1)
    batch = synthetic_batch(model, batch=2, spp=4, height=24, width=24, generator=g)
    target = torch.rand(2, 3, 24, 24, generator=g)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    before = [p.detach().clone() for p in model.parameters()]
    losses = []
    for _ in range(2):
        opt.zero_grad()
        out = model(batch)
        # Tonemapped L1, like most of the papers' losses; bounded so the smoke test is stable.
        loss = (out / (1 + out.abs()) - target / (1 + target)).abs().mean()
        loss.backward()
        grads = [p.grad for p in model.parameters() if p.requires_grad]
        assert any(gr is not None and gr.abs().sum() > 0 for gr in grads), "no gradient reached the weights"
        opt.step()
        losses.append(loss.item())
    assert all(math.isfinite(x) for x in losses)
    changed = sum(not torch.equal(b, p.detach()) for b, p in zip(before, model.parameters()))
    assert changed > 0


# ----------------------------------------------------------------------------- wiring: gradients

#: Models whose activations include plain ReLU (or ReLU after BatchNorm): a unit can be dead at
#: initialisation (all its outputs 0), and the weights reading it then get no gradient without any
#: wiring bug (measured: 10 of wskp_mr's small-preset convolutions read dead channels at 16x16).
#: Every other model uses leaky ReLU only, where no input channel of any layer may be without
#: gradient. A model not listed here gets the strict check.
PLAIN_RELU = {"kpcn", "dpcn", "kpcn_single", "wskp", "wskp_mr"}


def _record_live_inputs(model: torch.nn.Module) -> tuple[dict[str, torch.Tensor], list]:
    """Forward pre-hooks on every Conv2d/Linear: name -> (C_in,) bool, True where that input
    channel was non-zero somewhere in any call."""
    live: dict[str, torch.Tensor] = {}
    handles = []
    for name, mod in model.named_modules():
        if isinstance(mod, (torch.nn.Conv2d, torch.nn.Linear)):
            def hook(m: torch.nn.Module, args: tuple, name: str = name) -> None:
                x = args[0].detach()
                dims = [d for d in range(x.dim()) if d != 1] if isinstance(m, torch.nn.Conv2d) else list(range(x.dim() - 1))
                nz = x.ne(0).any(dim=dims[0]) if len(dims) == 1 else x.ne(0).sum(dim=dims).gt(0)
                live[name] = nz if name not in live else live[name] | nz
            handles.append(mod.register_forward_pre_hook(hook))
    return live, handles


@pytest.mark.parametrize("name", ALL)
def test_every_parameter_and_input_channel_gets_gradient(name: str) -> None:
    """Every parameter tensor gets a non-zero gradient, and so does every input-channel slice of
    every convolution weight (the weights that read one input channel).

    Catches dead branches and cut wiring: a U-Net step that never runs, a kernel head or a
    partitioner that ignores its context (its context projection gets no gradient), a kernel
    generator fed zeros instead of the layer embedding, coarse levels whose output is dropped,
    U-Net skip connections zeroed or scene features zeroed (the weight columns that read them get
    no gradient). Float64, so that no gradient underflows to 0 by accident. A frozen sub-model
    (refine's base: ``requires_grad`` off by design) is exempt, and must get no gradient at all.
    """
    torch.manual_seed(0)
    model = build_model(name, "small").train().double()
    g = torch.Generator().manual_seed(1)
    batch = synthetic_batch(model, batch=2, spp=3, height=16, width=16, generator=g, dtype=torch.float64)
    live, handles = _record_live_inputs(model)
    try:
        out = model(batch)
    finally:
        for h in handles:
            h.remove()
    # Random weights per output value, so that no gradient cancels by symmetry.
    (out * torch.rand(out.shape, generator=g, dtype=torch.float64)).sum().backward()
    dead = [n for n, p in model.named_parameters() if p.requires_grad and (p.grad is None or not p.grad.ne(0).any())]
    assert not dead, f"{name}: parameters without gradient: {dead}"
    leaked = [n for n, p in model.named_parameters() if not p.requires_grad and p.grad is not None]
    assert not leaked, f"{name}: frozen parameters with a gradient: {leaked}"
    modules = dict(model.named_modules())
    cut = []
    for mname, mod in modules.items():
        if not isinstance(mod, (torch.nn.Conv2d, torch.nn.Linear)) or mname not in live or not mod.weight.requires_grad:
            continue
        grad = mod.weight.grad
        per_in = grad.ne(0).transpose(0, 1).reshape(grad.shape[1], -1).any(dim=1)
        bad = ~per_in
        if name in PLAIN_RELU:
            bad &= live[mname]  # a dead ReLU unit upstream, not a wiring bug
        if bad.any():
            cut.append((mname, bad.nonzero().flatten().tolist(), grad.shape[1]))
    assert not cut, f"{name}: weights reading these input channels get no gradient (module, channels, of): {cut}"


# ----------------------------------------------------------------------------- wiring: inputs


def _input_groups(model: torch.nn.Module) -> list[str]:
    groups = list(model.required_channels())
    if model.input_kind == "samples" and "scene_features" not in groups:
        groups.append("scene_features")
    return groups


@pytest.mark.parametrize("name", ALL)
def test_output_depends_on_every_input_group(name: str) -> None:
    """Replacing any one input group (each declared channel, its variance, and scene features for
    sample models) by another plausible draw changes the output.

    Catches a feature that is declared and read but never reaches the output: scene features
    zeroed, a variance or guide dropped from the feature stack, a channel overwritten by another.
    Float64: a real dependence moves the output by >= 1e-7 relative here (KPCN's specular
    variance is the weakest, measured 1.3e-7 in float32); a cut one moves it by exactly 0.
    """
    torch.manual_seed(0)
    model = build_model(name, "small").eval().double()
    kw = dict(batch=1, spp=2, height=12, width=12, dtype=torch.float64)
    batch = synthetic_batch(model, generator=torch.Generator().manual_seed(1), **kw)
    other = synthetic_batch(model, generator=torch.Generator().manual_seed(2), **kw)
    with torch.no_grad():
        base = model(batch)
        scale = base.abs().max()
        unused = []
        for group in _input_groups(model):
            changed = dict(batch)
            changed[group] = other[group]
            delta = (model(changed) - base).abs().max() / scale
            if not delta > 1e-10:
                unused.append((group, float(delta)))
    assert not unused, f"{name}: output does not depend on {unused}"


#: Colour buffers whose values are HDR (unbounded).
_HDR = ("radiance", "diffuse", "specular", "oidn")


def _network_inputs(model: torch.nn.Module, batch: dict[str, torch.Tensor]) -> list[torch.Tensor]:
    f = model.features(batch)
    if isinstance(f, tuple):
        f = f[0]  # (features, radiance to filter)
    if isinstance(f, dict):
        # KPCN's diffuse branch sees irradiance c / (albedo + eps) without a log: the paper
        # transforms only the specular colour (Sec. 4.3), so that branch is not compressed.
        return [v for k, v in f.items() if k != "diffuse"]
    return [f]


@pytest.mark.parametrize("name", ALL)
def test_hdr_colour_enters_the_network_compressed(name: str) -> None:
    """The network never sees raw HDR radiance: with every colour buffer multiplied by 1e6 the
    network input stays below 1e3 (log(1 + 2e7) = 17; a variance of logs stays below 17^2).

    Catches radiance fed without log compression (or tonemapping), which makes a firefly of
    1e4 dominate every activation of an untrained network and its gradients.
    """
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    batch = synthetic_batch(model, batch=1, spp=2, height=8, width=8, generator=torch.Generator().manual_seed(1))
    for k in list(batch):
        if k in _HDR:
            batch[k] = batch[k] * 1e6
    with torch.no_grad():
        inputs = _network_inputs(model, batch)
    assert inputs, f"{name}: no network input to check"
    worst = max(float(x.abs().max()) for x in inputs)
    assert worst < 1e3, f"{name}: HDR colour x1e6 reaches the network as {worst:.3g}"


# ----------------------------------------------------------------------------- seeds and dtypes


@pytest.mark.parametrize("name", ALL)
def test_seed_dtype_and_inputs_left_alone(name: str) -> None:
    """One torch seed gives one set of weights; forward is a pure function of its inputs (no
    global RNG draw, no in-place change of the batch); float64 weights and inputs give a float64
    output that agrees with float32.

    Catches: initialisation from an unseeded generator, random draws inside forward (a training
    run could not be replayed), in-place ops writing into the caller's buffers, constants created
    as float32 that silently down-cast a float64 run (or fail on it).
    """
    torch.manual_seed(5)
    a = build_model(name, "small").eval()
    torch.manual_seed(5)
    b = build_model(name, "small").eval()
    torch.manual_seed(6)
    c = build_model(name, "small").eval()
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    # Parameter initialisation is single-threaded RNG: bitwise equal by construction.
    assert all(torch.equal(sa[k], sb[k]) for k in sa), f"{name}: same seed, different weights"
    assert any(not torch.equal(sa[k], sc[k]) for k in sa if sa[k].is_floating_point()), f"{name}: seed ignored"

    batch = synthetic_batch(a, batch=1, spp=2, height=10, width=12, generator=torch.Generator().manual_seed(1))
    copy = {k: v.clone() for k, v in batch.items()}
    with torch.no_grad():
        torch.manual_seed(100)
        y1 = a(batch)
        torch.rand(1000)  # move the global RNG on: forward must not depend on it
        y2 = a(batch)
        y64 = a.double()({k: v.double() for k, v in batch.items()})
    for k in batch:
        assert torch.equal(batch[k], copy[k]), f"{name}: forward modified input {k!r} in place"
    # Same inputs, same thread count: differences can only come from RNG use, never rounding.
    torch.testing.assert_close(y2, y1, rtol=1e-6, atol=1e-7)
    assert y64.dtype == torch.float64, f"{name}: float64 run returned {y64.dtype}"
    err = ((y64 - y1.double()).abs().max() / y64.abs().max()).item()
    assert err < 1e-4, f"{name}: float32 and float64 outputs differ by {err:.3g} of the maximum"
