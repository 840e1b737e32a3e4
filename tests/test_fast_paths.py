"""The fast inference switch (mcdenoise/models/inference.py) against the plain reference.

Every registered model is run twice on the same float64 input: reference (eval, no_grad, nothing
folded) and fast (inference_mode, RepVGG folded, channels_last where asked). float64 makes the
comparison test the algebra of each fast path, not float32 rounding; one float32 case bounds the
error the folded WSKP actually makes. The ops' own fast paths (separable box-sum importance
filter, chunked and banded splatting, loop gather) are tested against their references in
tests/test_ops_*.py.
"""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from mcdenoise.models.inference import denoise_batch, inference_context, prepare_inference
from mcdenoise.models.registry import build_model, list_models, synthetic_batch

from test_model_wskp import _randomise_bn  # noqa: E402  (one copy of the BN randomiser)

ALL = [e.name for e in list_models()]


def _pair(name: str, preset: str = "small", dtype: torch.dtype = torch.float64) -> tuple[nn.Module, nn.Module, dict]:
    torch.manual_seed(0)
    ref = build_model(name, preset).to(dtype)
    _randomise_bn(ref)
    fast = copy.deepcopy(ref)
    batch = synthetic_batch(ref, spp=3, height=20, width=18, dtype=dtype, generator=torch.Generator().manual_seed(1))
    return prepare_inference(ref, fast=False), prepare_inference(fast, fast=True), batch


@pytest.mark.parametrize("name", ALL)
def test_fast_equals_reference_float64(name: str) -> None:
    """Bug caught: a fast path (folding, inference_mode, the banded no-grad paths it enables)
    that changes a model's output."""
    ref, fast, batch = _pair(name)
    want = denoise_batch(ref, batch, fast=False)
    got = denoise_batch(fast, batch, fast=True)
    assert got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-11)


def test_wskp_paper_folded_float32_close_to_float64_reference() -> None:
    """Bug caught: a fold that is exact in float64 but loses accuracy in float32 (e.g. BN scales
    applied after summing branches of very different magnitude)."""
    ref, _, batch = _pair("wskp", "paper")
    want = denoise_batch(ref, batch, fast=False)
    _, fast32, _ = _pair("wskp", "paper", torch.float32)
    got = denoise_batch(fast32, {k: v.float() for k, v in batch.items()}, fast=True).double()
    err = (got - want).abs().max() / want.abs().max()
    assert err < 1e-4, f"folded float32 WSKP differs from the float64 reference by {err:.2e} (relative to max)"


@pytest.mark.parametrize("name", ["wskp", "kpcn", "layer_optimized"])
def test_channels_last_equals_reference(name: str) -> None:
    """Bug caught: an op inside the model that assumes contiguous NCHW memory (view on a permuted
    tensor, data_ptr arithmetic) and goes wrong with channels_last weights."""
    ref, _, batch = _pair(name)
    fast = prepare_inference(copy.deepcopy(ref), fast=True, channels_last=True)
    conv = next(m for m in fast.modules() if isinstance(m, nn.Conv2d) and m.kernel_size != (1, 1))
    assert conv.weight.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(denoise_batch(fast, batch), denoise_batch(ref, batch, fast=False), rtol=1e-9, atol=1e-11)


def test_switch_is_applied() -> None:
    """Bug caught: a `fast` flag that silently does nothing (no inference mode, no folding) or a
    reference path that folds (then the parity tests compare the fast path with itself)."""
    ref, fast, batch = _pair("wskp")
    assert all(b.fused is None for b in ref.net) and all(b.fused is not None for b in fast.net)
    assert not ref.training and not fast.training
    with inference_context(True):
        assert torch.is_inference(fast(batch))
    with inference_context(False):
        out = ref(batch)
        assert not torch.is_inference(out) and not out.requires_grad


def test_prepare_inference_default_channels_last_cpu_off() -> None:
    """Bug caught: channels_last switched on for CPU models by default, where it was not measured
    to pay (the docstring's claim)."""
    model = prepare_inference(build_model("kpcn", "small"))
    conv = next(m for m in model.modules() if isinstance(m, nn.Conv2d) and m.kernel_size != (1, 1))
    assert conv.weight.is_contiguous()


# -- PointwiseConv: the 1x1 convolution as a batched matrix product (models/blocks.py) --------


@pytest.mark.parametrize("bias", [True, False])
def test_pointwise_conv_equals_conv2d_float64(bias: bool) -> None:
    """Bug caught: a transposed weight view, the bias added on the wrong axis, or samples mixed
    by the (N, C, H*W) reshape (N > 1 and non-square H x W make each of those visible)."""
    from mcdenoise.models.blocks import PointwiseConv

    torch.manual_seed(0)
    conv = PointwiseConv(5, 7, bias=bias).double()
    with torch.no_grad():
        if bias:
            conv.bias.normal_()
    x = torch.randn(3, 5, 4, 6, dtype=torch.float64)
    torch.testing.assert_close(conv(x), torch.nn.functional.conv2d(x, conv.weight, conv.bias), rtol=1e-12, atol=1e-12)
    # Non-contiguous input (a channel slice, channels_last) takes the same path.
    xl = torch.randn(3, 9, 4, 6, dtype=torch.float64)[:, 2:7]
    torch.testing.assert_close(conv(xl), torch.nn.functional.conv2d(xl, conv.weight, conv.bias), rtol=1e-12, atol=1e-12)
    xc = x.contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(conv(xc), torch.nn.functional.conv2d(x, conv.weight, conv.bias), rtol=1e-12, atol=1e-12)
    # An NHWC input (a bfloat16 trunk's) gives NHWC back: no copy to NCHW on the way (campaign 11).
    assert conv(xc).is_contiguous(memory_format=torch.channels_last)


def test_pointwise_conv_gradcheck_and_state_dict() -> None:
    """Bug caught: a forward whose gradients differ from its values' (an expand without the sum
    over the batch in the weight gradient), or a module whose state dict no longer loads
    weights trained with nn.Conv2d (the shipped weights)."""
    from mcdenoise.models.blocks import PointwiseConv

    torch.manual_seed(0)
    conv = PointwiseConv(3, 2).double()
    x = torch.randn(2, 3, 3, 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, w, b: torch.nn.functional.conv2d(a, w, b), (x, conv.weight, conv.bias))
    assert torch.autograd.gradcheck(lambda a: conv(a), (x,))
    params = (conv.weight.detach().clone().requires_grad_(), conv.bias.detach().clone().requires_grad_())
    assert torch.autograd.gradcheck(
        lambda wt, b: torch.func.functional_call(conv, {"weight": wt, "bias": b}, (x.detach(),)), params)
    plain = nn.Conv2d(3, 2, 1)
    conv.load_state_dict(plain.state_dict())
    torch.testing.assert_close(conv(x.float().detach().double()).float(), plain(x.detach().float()), rtol=1e-5, atol=1e-6)


# -- precision="bfloat16": convolution trunks in bfloat16 and channels_last ------------------


@pytest.mark.parametrize("name", ALL)
def test_bfloat16_trunks_close_to_float32(name: str) -> None:
    """Bug caught: a trunk name that no longer resolves (silently no speed-up), a trunk whose
    output comes back in bfloat16 or channels_last into float32 kernel code, or a model part
    that must stay float32 (exponentials, normalisations) wrapped by mistake: its error would be
    far above bfloat16's ~0.4 % per value."""
    from mcdenoise.models.inference import ReducedPrecision

    torch.manual_seed(0)
    ref = build_model(name, "small")
    _randomise_bn(ref)
    low = copy.deepcopy(ref)
    batch = synthetic_batch(ref, spp=3, height=20, width=18, generator=torch.Generator().manual_seed(1))
    prepare_inference(ref, fast=True)
    prepare_inference(low, fast=True, precision="bfloat16")
    wrapped = [m for m in low.modules() if isinstance(m, ReducedPrecision)]
    assert wrapped, f"{name}: no convolution trunk runs in bfloat16"
    assert all(p.dtype == torch.bfloat16 for m in wrapped for p in m.parameters())
    want = denoise_batch(ref, batch)
    got = denoise_batch(low, batch)
    assert got.dtype == torch.float32 and got.is_contiguous()
    err = ((got - want).abs().max() / want.abs().max()).item()
    assert err < 0.05, f"{name}: bfloat16 trunks differ by {err:.3f} of the image maximum"


def test_precision_only_with_fast_and_resolves() -> None:
    """Bug caught: the reference path (fast=False) picking up bfloat16, or an unknown precision
    accepted silently."""
    from mcdenoise.models.inference import ReducedPrecision, resolve_precision

    m = prepare_inference(build_model("wskp", "small"), fast=False, precision="bfloat16")
    assert not any(isinstance(x, ReducedPrecision) for x in m.modules())
    assert resolve_precision(None) == "float32" and resolve_precision("bfloat16") == "bfloat16"
    assert resolve_precision("auto") in ("float32", "bfloat16")
    with pytest.raises(ValueError, match="precision 'fp8'"):
        resolve_precision("fp8")


@pytest.mark.parametrize("band_bytes", [1, 500, 1 << 30])
def test_convert_layout_equals_to(band_bytes: int) -> None:
    """Bug caught: the banded NCHW <-> channels_last copy dropping or shifting rows (bands of one
    row, several rows with a short last band, the whole tensor)."""
    from mcdenoise.models.inference import convert_layout

    x = torch.randn(2, 5, 7, 3)
    cl = convert_layout(x, torch.bfloat16, torch.channels_last, band_bytes=band_bytes)
    assert cl.is_contiguous(memory_format=torch.channels_last) and cl.dtype == torch.bfloat16
    assert torch.equal(cl, x.to(torch.bfloat16))
    back = convert_layout(cl, torch.float32, torch.contiguous_format, band_bytes=band_bytes)
    assert back.is_contiguous() and torch.equal(back, x.to(torch.bfloat16).float())


@pytest.mark.parametrize("name", ["kpcn", "sbmc", "layer", "wskp"])
def test_bfloat16_shipped_weights_close_to_float32(name: str) -> None:
    """Bug caught: bfloat16 trunks that only look harmless on random weights (trained weights
    have larger logits, where a cast error is amplified by the exponential). The test-split
    metrics of both precisions are in docs/PERFORMANCE.md; this bounds the per-image difference."""
    from mcdenoise.models.weights import load_denoiser

    ref, _ = load_denoiser(name)
    low, _ = load_denoiser(name)
    prepare_inference(ref, fast=True)
    prepare_inference(low, fast=True, precision="bfloat16")
    g = torch.Generator().manual_seed(5)
    batch = synthetic_batch(ref, spp=4, height=40, width=36, generator=g)
    want, got = denoise_batch(ref, batch), denoise_batch(low, batch)
    rel = (((got - want) ** 2) / (want**2 + 1e-2)).mean().item()
    assert rel < 1e-3, f"{name}: bfloat16 differs from float32 by relMSE {rel:.2e}"


def _thp_mode() -> str | None:
    try:
        text = open("/sys/kernel/mm/transparent_hugepage/enabled").read()
    except OSError:
        return None
    return text[text.index("[") + 1 : text.index("]")]


@pytest.mark.skipif(_thp_mode() not in ("madvise", "always"), reason="needs Linux transparent huge pages")
def test_import_puts_large_tensors_on_huge_pages() -> None:
    """Bug caught: the huge-page switch set after torch's first large allocation (or dropped), so
    every fresh per-sample tensor is written at page-fault speed again (SBMC 26 % slower)."""
    import subprocess
    import sys

    code = ("import mcdenoise, torch; t = torch.empty(64 << 20, dtype=torch.uint8); t.fill_(1); "
            "print(next(int(l.split()[1]) for l in open('/proc/self/smaps_rollup') if l.startswith('AnonHugePages')))")
    env = {k: v for k, v in __import__("os").environ.items() if k != "THP_MEM_ALLOC_ENABLE"}
    on = int(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout)
    assert on >= 32 << 10, f"only {on} KiB of the 64 MiB tensor is on huge pages"
    if _thp_mode() == "madvise":  # off: torch does not ask for huge pages, the kernel gives none
        off = int(subprocess.run([sys.executable, "-c", code], env={**env, "THP_MEM_ALLOC_ENABLE": "0"},
                                 capture_output=True, text=True, check=True).stdout)
        assert off < on


@pytest.mark.parametrize("preset", ["ens_kpcn", "kpcn", "own"])
def test_a_nested_kernel_model_keeps_its_trunk_layout_rule(preset: str) -> None:
    """Bug caught (campaign 10): a combiner's kernel candidate (kpcn) had its bfloat16 trunks'
    outputs converted back to the contiguous layout because the combiner itself does not declare
    ``trunk_outputs_any_layout`` (2.2x slower at 1080p); the nearest declaring module must decide.
    The combiner's own trunk keeps its bfloat16 channels_last output too (``own``: 52 channels,
    whose whole-image conversion cost more than the network). Also the fast paths of a combiner with a nested model: float64 equality and bfloat16 closeness."""
    from mcdenoise.models.inference import ReducedPrecision

    ref, fast, batch = _pair("combine", preset)
    torch.testing.assert_close(denoise_batch(fast, batch), denoise_batch(ref, batch, fast=False), rtol=1e-9, atol=1e-11)
    torch.manual_seed(0)
    f32 = prepare_inference(build_model("combine", preset), fast=True)
    low = prepare_inference(copy.deepcopy(f32), fast=True, precision="bfloat16")
    restore = {n: m.restore_output for n, m in low.named_modules() if isinstance(m, ReducedPrecision)}
    assert restore["net"] is False  # the combiner converts its few weight channels itself
    kernel_trunks = [n for n in restore if n.startswith("kernel_model.")]
    assert (preset == "own") == (not kernel_trunks) and not any(restore[n] for n in kernel_trunks)
    batch = synthetic_batch(f32, height=20, width=18, generator=torch.Generator().manual_seed(1))
    want, got = denoise_batch(f32, batch), denoise_batch(low, batch)
    assert ((got - want).abs().max() / want.abs().max()).item() < 0.05
