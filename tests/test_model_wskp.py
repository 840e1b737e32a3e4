"""WSKP and wskp_mr: RepVGG re-parameterisation, ImportanceNet sizes, demodulation, Eq. 7 blend."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from mcdenoise.models import wskp as wskp_module
from mcdenoise.models.registry import build_model, synthetic_batch
from mcdenoise.models.wskp import RepVGGBlock, tonemap_ldr
from mcdenoise.ops.temporal import temporal_accumulate

EPS = 0.00316


def _randomise_bn(model: nn.Module, seed: int = 0) -> None:
    """Non-trivial BN statistics and affine parameters, so folding has something to fold."""
    g = torch.Generator().manual_seed(seed)
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            with torch.no_grad():
                n = m.num_features
                m.weight.copy_(0.5 + torch.rand(n, generator=g))
                m.bias.copy_(torch.randn(n, generator=g) * 0.1)
                m.running_mean.copy_(torch.randn(n, generator=g) * 0.1)
                m.running_var.copy_(0.5 + torch.rand(n, generator=g))


def test_repvgg_block_fold_float64_exact() -> None:
    torch.manual_seed(0)
    for cin, cout, act in ((6, 6, True), (10, 14, True), (14, 12, False)):
        block = RepVGGBlock(cin, cout, activation=act).double()
        _randomise_bn(block)
        block.eval()
        x = torch.randn(2, cin, 9, 7, dtype=torch.float64)
        with torch.no_grad():
            before = block(x)
            block.reparameterize()
            after = block(x)
        assert block.fused is not None and block.fused.kernel_size == (5, 5)
        assert not any(isinstance(m, nn.BatchNorm2d) for m in block.modules())
        torch.testing.assert_close(after, before, rtol=1e-12, atol=1e-12)


def test_reparameterize_changes_output_by_at_most_1e5_relative() -> None:
    torch.manual_seed(0)
    model = build_model("wskp", "paper")
    # A few training-mode passes give BN real running statistics.
    for seed in range(3):
        b = synthetic_batch(model, batch=2, height=16, width=16, generator=torch.Generator().manual_seed(seed))
        with torch.no_grad():
            model.train()(b)
    _randomise_bn(model)
    model.eval()
    b = synthetic_batch(model, batch=2, height=19, width=21, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        imp0, fus0 = model.predict(b)
        before = model(b)
        model.reparameterize()
        imp1, fus1 = model.predict(b)
        after = model(b)
    convs = [m for m in model.modules() if isinstance(m, nn.Conv2d)]
    assert len(convs) == 6 and all(c.kernel_size == (5, 5) for c in convs)
    rel = ((after - before).abs().max() / before.abs().max()).item()
    assert rel <= 1e-5, rel
    assert ((imp1 - imp0).abs().max() / imp0.abs().max()).item() <= 1e-5
    assert ((fus1 - fus0).abs().max() / fus0.abs().max()).item() <= 1e-5


def test_importance_net_sizes_follow_figure_2() -> None:
    for preset, blocks in (("paper", 6), ("paper3", 3)):
        model = build_model("wskp", preset)
        net = list(model.net)
        assert len(net) == blocks
        assert net[0].in_ch == 10
        assert [blk.out_ch for blk in net] == [14] * (blocks - 1) + [12]
        assert [blk.activation for blk in net] == [True] * (blocks - 1) + [False]
        assert tuple(model.config.kernel_sizes) == (3, 5, 7, 9, 11, 13)
        # 5x5 + 3x3 + 1x1 branches of each block: 35 weights per in/out channel pair.
        convs = sum(blk.in_ch * blk.out_ch * 35 for blk in net)
        bns = sum(2 * blk.out_ch * (3 + (blk.identity is not None)) for blk in net)
        assert sum(p.numel() for p in model.parameters()) == convs + bns
    assert set(build_model("wskp", "small").required_channels()) == {"radiance", "albedo", "normal", "depth"}


def test_network_input_is_ldr_and_scaled() -> None:
    model = build_model("wskp", "small")
    b = synthetic_batch(model, batch=2, height=8, width=8)
    b["radiance"][0, :, 0, 0] = 1e4  # a firefly stays in [0, 1)
    x = model.features(b)
    assert x.shape == (2, 10, 8, 8)
    assert x.min() >= 0 and x.max() <= 1
    torch.testing.assert_close(x[:, :3], tonemap_ldr(b["radiance"]))
    torch.testing.assert_close(x[:, 3:6], b["albedo"])
    torch.testing.assert_close(x[:, 6:9], (b["normal"] + 1) / 2)
    torch.testing.assert_close(x[:, 9].amax(dim=(1, 2)), torch.ones(2))


def test_constant_irradiance_is_preserved_through_demodulation() -> None:
    """Normalised kernels on the demodulated signal: a constant irradiance gives back the radiance
    exactly, texture included, whatever the (random) network predicts -- for wskp and wskp_mr."""
    torch.manual_seed(0)
    for name, size in (("wskp", (11, 13)), ("wskp_mr", (11, 13)), ("wskp_mr", (16, 16))):
        model = build_model(name, "small").eval()
        b = synthetic_batch(model, height=size[0], width=size[1])
        b["radiance"] = 2.5 * (b["albedo"] + EPS)
        with torch.no_grad():
            out = model(b)
        torch.testing.assert_close(out, b["radiance"], rtol=1e-5, atol=1e-6)


def test_hdr_filtering_is_linear_in_radiance_for_fixed_prediction() -> None:
    """The kernels filter HDR irradiance: with the prediction fixed, the output scales with the input."""
    model = build_model("wskp", "small").eval()
    b = synthetic_batch(model, height=10, width=10)
    with torch.no_grad():
        imp, fus = model.predict(b)
        from mcdenoise.ops.importance import fused_importance_filter

        irr = b["radiance"] / (b["albedo"] + EPS)
        want = fused_importance_filter(irr, imp, fus, sizes=(3, 5, 7)) * (b["albedo"] + EPS)
        torch.testing.assert_close(model(b), want)
        torch.testing.assert_close(
            fused_importance_filter(100 * irr, imp, fus, sizes=(3, 5, 7)), 100 * want / (b["albedo"] + EPS)
        )


def test_wskp_mr_levels_and_eq7_heads() -> None:
    model = build_model("wskp_mr", "paper")
    assert model.levels == 3 and tuple(model.config.kernel_sizes) == (3, 5)
    # 2 importance + 2 fusion logits per level, + 1 blend weight below the coarsest level.
    assert [h.out_channels for h in model.heads] == [5, 5, 4]


def test_temporal_accumulation_is_exposed_and_separate() -> None:
    assert wskp_module.temporal_accumulate is temporal_accumulate
    model = build_model("wskp", "small")
    assert model.temporal_accumulate is temporal_accumulate
    # It is not part of the per-frame inputs.
    assert "motion" not in model.required_channels()


def test_missing_channel_named_and_folded_checkpoint_loads() -> None:
    model = build_model("wskp", "small")
    b = synthetic_batch(model, height=6, width=6)
    del b["depth"]
    with pytest.raises(ValueError, match="depth"):
        model(b)
    folded = build_model("wskp", "small").reparameterize()
    fresh = build_model("wskp", "small").reparameterize()
    fresh.load_state_dict(folded.state_dict())
    b = synthetic_batch(model, height=6, width=6)
    with torch.no_grad():
        torch.testing.assert_close(fresh(b), folded(b))
