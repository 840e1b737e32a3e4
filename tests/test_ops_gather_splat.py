"""Gather, splat and kernel activations: fast paths vs references (float64), gradients, identities."""

from __future__ import annotations

import pytest
import torch

from conftest import DEVICES

from mcdenoise.ops import (
    SplatAccumulator,
    exp_kernel,
    gather,
    gather_reference,
    get_default_impl,
    normalize_splat,
    softmax_kernel,
    splat,
    splat_reference,
    use_impl,
)

F64 = torch.float64


def _noncontig(x: torch.Tensor) -> torch.Tensor:
    """Same values, non-contiguous layout (a transposed copy transposed back)."""
    y = x.transpose(-1, -2).contiguous().transpose(-1, -2)
    assert not y.is_contiguous() and torch.equal(y, x)
    return y


def _delta_kernel(shape: tuple[int, ...], k: int, dim: int, **kw) -> torch.Tensor:
    w = torch.zeros(shape, **kw)
    w.select(dim, (k * k) // 2).fill_(1.0)
    return w


# ---------------------------------------------------------------- gather


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("k", [1, 3, 5, 7])
@pytest.mark.parametrize("c", [1, 3])
def test_gather_fast_matches_reference(device: str, k: int, c: int) -> None:
    g = torch.Generator().manual_seed(k * 10 + c)
    x = torch.randn(2, c, 7, 9, generator=g, dtype=F64).to(device)
    w = torch.randn(2, k * k, 7, 9, generator=g, dtype=F64).to(device)
    ref = gather_reference(x, w)
    fast = gather(x, w, impl="fast")
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(gather(_noncontig(x), _noncontig(w), impl="fast"), ref, rtol=1e-12, atol=1e-12)


def test_gather_kernel_larger_than_image() -> None:
    g = torch.Generator().manual_seed(1)
    x = torch.randn(1, 3, 6, 5, generator=g, dtype=F64)
    w = torch.randn(1, 21 * 21, 6, 5, generator=g, dtype=F64)
    torch.testing.assert_close(gather(x, w, impl="fast"), gather_reference(x, w), rtol=1e-12, atol=1e-12)


def test_gather_matches_explicit_loop() -> None:
    # Independent of unfold: the definition written out with Python loops.
    g = torch.Generator().manual_seed(2)
    k, r = 3, 1
    x = torch.randn(1, 2, 4, 5, generator=g, dtype=F64)
    w = torch.randn(1, k * k, 4, 5, generator=g, dtype=F64)
    expect = torch.zeros_like(x)
    for y in range(4):
        for xx in range(5):
            for i in range(k):
                for j in range(k):
                    yy, xs = y + i - r, xx + j - r
                    if 0 <= yy < 4 and 0 <= xs < 5:
                        expect[0, :, y, xx] += w[0, i * k + j, y, xx] * x[0, :, yy, xs]
    torch.testing.assert_close(gather_reference(x, w), expect, rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(gather(x, w, impl="fast"), expect, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("impl", ["fast", "reference"])
def test_gather_gradcheck(device: str, impl: str) -> None:
    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, 2, 3, 4, generator=g, dtype=F64).to(device).requires_grad_()
    w = torch.randn(2, 9, 3, 4, generator=g, dtype=F64).to(device).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: gather(a, b, impl=impl), (x, w))


def test_gather_gradgradcheck_fast() -> None:
    g = torch.Generator().manual_seed(4)
    x = torch.randn(1, 2, 4, 4, generator=g, dtype=F64, requires_grad=True)
    w = torch.randn(1, 9, 4, 4, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradgradcheck(lambda a, b: gather(a, b, impl="fast"), (x, w))


@pytest.mark.parametrize("impl", ["fast", "reference"])
def test_gather_centre_delta_is_identity(impl: str) -> None:
    x = torch.randn(2, 3, 6, 7, dtype=F64)
    w = _delta_kernel((2, 25, 6, 7), 5, 1, dtype=F64)
    torch.testing.assert_close(gather(x, w, impl=impl), x, rtol=0, atol=0)


def test_gather_of_delta_image_reads_flipped_kernels() -> None:
    # out[p] = w[p, tap with p + d = q]: pixel p reads the impulse at q through tap d = q - p.
    k, r = 5, 2
    x = torch.zeros(1, 1, 9, 9, dtype=F64)
    x[0, 0, 4, 4] = 1.0
    w = torch.randn(1, k * k, 9, 9, dtype=F64)
    out = gather(x, w, impl="fast")
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            py, px = 4 - dy, 4 - dx
            assert out[0, 0, py, px].item() == pytest.approx(w[0, (dy + r) * k + (dx + r), py, px].item(), abs=1e-15)


def test_gather_constant_image_normalised_kernels() -> None:
    w = softmax_kernel(torch.randn(2, 49, 11, 12, dtype=F64))
    x = torch.full((2, 3, 11, 12), 2.5, dtype=F64)
    out = gather(x, w, impl="fast")
    # Away from the border every tap reads the constant; at the border the zero padding shows.
    torch.testing.assert_close(out[..., 3:-3, 3:-3], x[..., 3:-3, 3:-3], rtol=1e-13, atol=1e-13)
    assert out[0, 0, 0, 0].item() < 2.5 - 1e-3


@pytest.mark.parametrize(
    "image_shape, weight_shape, needle",
    [
        ((2, 3, 8), (2, 9, 8, 8), "image must have shape (B, C, H, W)"),
        ((2, 3, 8, 8), (2, 9, 8), "weights must have shape (B, K*K, H, W)"),
        ((2, 3, 8, 8), (2, 8, 8, 8), "K*K taps for an odd K, got 8"),
        ((2, 3, 8, 8), (2, 16, 8, 8), "K*K taps for an odd K, got 16"),
        ((2, 3, 8, 8), (2, 9, 8, 7), "(2, K*K, 8, 8)"),
        ((2, 3, 8, 8), (1, 9, 8, 8), "(2, K*K, 8, 8)"),
    ],
)
@pytest.mark.parametrize("impl", ["fast", "reference"])
def test_gather_bad_input(image_shape, weight_shape, needle: str, impl: str) -> None:
    with pytest.raises(ValueError) as err:
        gather(torch.zeros(image_shape), torch.zeros(weight_shape), impl=impl)
    assert needle in str(err.value)


def test_impl_switch(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib

    # The package re-exports functions named like their modules, so fetch the modules themselves.
    gather_mod = importlib.import_module("mcdenoise.ops.gather")
    splat_mod = importlib.import_module("mcdenoise.ops.splat")

    calls: list[str] = []
    monkeypatch.setattr(gather_mod, "gather_reference", lambda *a: calls.append("gather") or torch.zeros(1))
    monkeypatch.setattr(splat_mod, "splat_reference", lambda *a: calls.append("splat") or (torch.zeros(1),) * 2)
    x, w = torch.zeros(1, 1, 3, 3), torch.zeros(1, 9, 3, 3)
    assert get_default_impl() == "auto"
    gather(x, w)
    splat(x[:, None], w[:, None])
    assert calls == []
    with use_impl("reference"):
        assert get_default_impl() == "reference"
        gather(x, w)
        splat(x[:, None], w[:, None])
        gather(x, w, impl="fast")  # an explicit choice wins over the switch
    assert calls == ["gather", "splat"]
    assert get_default_impl() == "auto"
    with pytest.raises(ValueError, match="impl must be one of"):
        gather(torch.zeros(1, 1, 3, 3), torch.zeros(1, 9, 3, 3), impl="triton-someday")


# ---------------------------------------------------------------- splat


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("k", [1, 3, 5])
@pytest.mark.parametrize("c", [1, 3])
@pytest.mark.parametrize("chunk", [1, 2, None])
def test_splat_fast_matches_reference(device: str, k: int, c: int, chunk: int | None) -> None:
    g = torch.Generator().manual_seed(k * 100 + c)
    v = torch.randn(2, 3, c, 7, 6, generator=g, dtype=F64).to(device)
    w = torch.randn(2, 3, k * k, 7, 6, generator=g, dtype=F64).to(device)
    num_r, ws_r = splat_reference(v, w)
    num_f, ws_f = splat(_noncontig(v), _noncontig(w), chunk=chunk, impl="fast")
    torch.testing.assert_close(num_f, num_r, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ws_f, ws_r, rtol=1e-12, atol=1e-12)
    assert num_f.shape == (2, c, 7, 6) and ws_f.shape == (2, 1, 7, 6)


def test_splat_matches_explicit_loop() -> None:
    g = torch.Generator().manual_seed(5)
    k, r = 3, 1
    v = torch.randn(1, 2, 2, 4, 5, generator=g, dtype=F64)
    w = torch.rand(1, 2, k * k, 4, 5, generator=g, dtype=F64)
    num = torch.zeros(1, 2, 4, 5, dtype=F64)
    ws = torch.zeros(1, 1, 4, 5, dtype=F64)
    for s in range(2):
        for y in range(4):
            for x in range(5):
                for i in range(k):
                    for j in range(k):
                        ty, tx = y + i - r, x + j - r
                        if 0 <= ty < 4 and 0 <= tx < 5:
                            num[0, :, ty, tx] += w[0, s, i * k + j, y, x] * v[0, s, :, y, x]
                            ws[0, 0, ty, tx] += w[0, s, i * k + j, y, x]
    for impl in ("fast", "reference"):
        n2, w2 = splat(v, w, impl=impl)
        torch.testing.assert_close(n2, num, rtol=1e-13, atol=1e-13)
        torch.testing.assert_close(w2, ws, rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("impl,chunk", [("fast", 1), ("fast", 2), ("reference", None)])
def test_splat_gradcheck(device: str, impl: str, chunk: int | None) -> None:
    g = torch.Generator().manual_seed(6)
    # B = 2 and S = 3 so that chunking and batch indexing are both exercised, kept tiny for speed.
    v = torch.randn(2, 3, 1, 3, 4, generator=g, dtype=F64).to(device).requires_grad_()
    w = torch.randn(2, 3, 9, 3, 4, generator=g, dtype=F64).to(device).requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: splat(a, b, chunk=chunk, impl=impl), (v, w))


def test_splat_gradgradcheck_fast() -> None:
    g = torch.Generator().manual_seed(7)
    v = torch.randn(1, 2, 1, 3, 3, generator=g, dtype=F64, requires_grad=True)
    w = torch.randn(1, 2, 9, 3, 3, generator=g, dtype=F64, requires_grad=True)
    assert torch.autograd.gradgradcheck(lambda a, b: splat(a, b, chunk=1, impl="fast"), (v, w))


@pytest.mark.parametrize("impl", ["fast", "reference"])
def test_splat_centre_delta(impl: str) -> None:
    v = torch.randn(2, 1, 3, 6, 7, dtype=F64)
    w = _delta_kernel((2, 1, 25, 6, 7), 5, 2, dtype=F64)
    torch.testing.assert_close(normalize_splat(*splat(v, w, impl=impl)), v[:, 0], rtol=1e-9, atol=1e-12)
    # Several samples with centre-only kernels of equal weight: the per-pixel sample mean.
    v4 = torch.randn(2, 4, 3, 6, 7, dtype=F64)
    w4 = _delta_kernel((2, 4, 25, 6, 7), 5, 2, dtype=F64)
    torch.testing.assert_close(normalize_splat(*splat(v4, w4, impl=impl)), v4.mean(1), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("impl", ["fast", "reference"])
def test_splat_one_sample_reproduces_its_kernel(impl: str) -> None:
    k, r = 5, 2
    v = torch.zeros(1, 2, 1, 9, 9, dtype=F64)
    v[0, 1, 0, 4, 3] = 1.0
    w = torch.rand(1, 2, k * k, 9, 9, dtype=F64)
    num, _ = splat(v, w, impl=impl)
    footprint = num[0, 0, 4 - r : 4 + r + 1, 3 - r : 3 + r + 1]
    # Tap i * K + j lands at offset (i - r, j - r): the footprint is the kernel laid out as K x K.
    torch.testing.assert_close(footprint, w[0, 1, :, 4, 3].reshape(k, k), rtol=0, atol=0)
    mask = torch.ones(9, 9, dtype=torch.bool)
    mask[4 - r : 4 + r + 1, 3 - r : 3 + r + 1] = False
    assert torch.count_nonzero(num[0, 0][mask]) == 0


def test_splat_gather_adjoint() -> None:
    # <gather(x, w), y> = <x, splat(y, w)> for one sample per pixel: splat is gather's transpose.
    g = torch.Generator().manual_seed(8)
    x = torch.randn(2, 3, 7, 8, generator=g, dtype=F64)
    y = torch.randn(2, 3, 7, 8, generator=g, dtype=F64)
    w = torch.randn(2, 25, 7, 8, generator=g, dtype=F64)
    lhs = (gather(x, w, impl="fast") * y).sum()
    num, _ = splat(y.unsqueeze(1), w.unsqueeze(1), impl="fast")
    rhs = (x * num).sum()
    assert lhs.item() == pytest.approx(rhs.item(), rel=1e-12)


def test_splat_constant_image_stays_constant() -> None:
    # Normalised splat of a constant is the constant everywhere, borders included.
    w = exp_kernel(torch.randn(2, 3, 25, 9, 10, dtype=F64))
    v = torch.full((2, 3, 3, 9, 10), -1.75, dtype=F64)
    out = normalize_splat(*splat(v, w, impl="fast"), eps=0.0)
    torch.testing.assert_close(out, v[:, 0], rtol=1e-12, atol=1e-12)
    # ... and agrees with gather of the same constant with normalised kernels in the interior.
    gw = softmax_kernel(torch.randn(2, 25, 9, 10, dtype=F64))
    torch.testing.assert_close(gather(v[:, 0], gw)[..., 2:-2, 2:-2], out[..., 2:-2, 2:-2], rtol=1e-12, atol=1e-12)


def test_splat_sample_permutation_invariant() -> None:
    g = torch.Generator().manual_seed(9)
    v = torch.randn(1, 5, 3, 6, 6, generator=g, dtype=F64)
    w = torch.rand(1, 5, 9, 6, 6, generator=g, dtype=F64)
    perm = torch.tensor([3, 0, 4, 2, 1])
    a = normalize_splat(*splat(v, w, chunk=2))
    b = normalize_splat(*splat(v[:, perm], w[:, perm], chunk=2))
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_splat_accumulator_equals_one_splat() -> None:
    g = torch.Generator().manual_seed(10)
    v = torch.randn(2, 5, 3, 6, 7, generator=g, dtype=F64)
    w = torch.rand(2, 5, 9, 6, 7, generator=g, dtype=F64)
    acc = SplatAccumulator()
    for s0 in range(0, 5, 2):
        acc.add(v[:, s0 : s0 + 2], w[:, s0 : s0 + 2])
    num, ws = splat(v, w)
    torch.testing.assert_close(acc.result()[0], num, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(acc.normalized(), normalize_splat(num, ws), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="nothing was added"):
        SplatAccumulator().result()


@pytest.mark.parametrize(
    "v_shape, w_shape, needle",
    [
        ((2, 3, 8, 8), (2, 3, 9, 8, 8), "values must have shape (B, S, C, H, W)"),
        ((2, 3, 1, 8, 8), (2, 9, 8, 8), "weights must have shape (B, S, K*K, H, W)"),
        ((2, 3, 1, 8, 8), (2, 2, 9, 8, 8), "(2, 3, K*K, 8, 8)"),
        ((2, 3, 1, 8, 8), (2, 3, 10, 8, 8), "odd K, got 10"),
    ],
)
def test_splat_bad_input(v_shape, w_shape, needle: str) -> None:
    for impl in ("fast", "reference"):
        with pytest.raises(ValueError) as err:
            splat(torch.zeros(v_shape), torch.zeros(w_shape), impl=impl)
        assert needle in str(err.value)
    with pytest.raises(ValueError, match=r"wsum must have shape \(B, 1, H, W\)"):
        normalize_splat(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4))


# ---------------------------------------------------------------- kernel activations


def test_softmax_kernel_normalised_and_stable() -> None:
    logits = torch.randn(2, 9, 4, 5, dtype=F64) * 1e4
    w = softmax_kernel(logits)
    assert torch.isfinite(w).all()
    torch.testing.assert_close(w.sum(1), torch.ones(2, 4, 5, dtype=F64), rtol=1e-12, atol=1e-12)


def test_exp_kernel_per_image_max() -> None:
    x = torch.randn(2, 3, 9, 4, 5, dtype=F64) * 100 + 5000
    e = exp_kernel(x)
    assert torch.isfinite(e).all()
    torch.testing.assert_close(e.amax(dim=(1, 2, 3, 4)), torch.ones(2, dtype=F64), rtol=0, atol=0)
    # A per-image shift cancels in the normalised splat; a per-kernel shift would not.
    v = torch.randn(2, 3, 2, 4, 5, dtype=F64)
    lw = torch.randn(2, 3, 9, 4, 5, dtype=F64)
    shifted = lw + torch.tensor([3.0, -7.0], dtype=F64).reshape(2, 1, 1, 1, 1)
    a = normalize_splat(*splat(v, exp_kernel(lw)))
    torch.testing.assert_close(normalize_splat(*splat(v, exp_kernel(shifted))), a, rtol=1e-12, atol=1e-12)
    b = normalize_splat(*splat(v, torch.exp(lw - lw.amax(2, keepdim=True))))
    assert (a - b).abs().max() > 1e-3


def test_kernel_activations_gradcheck() -> None:
    x = torch.randn(2, 2, 9, 2, 1, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(exp_kernel, (x,))
    assert torch.autograd.gradcheck(lambda t: softmax_kernel(t, dim=2), (x,))


def test_fast_path_memory_does_not_keep_unfold() -> None:
    # Autograd keeps only the inputs for the fast gather: the graph holds no K*K x C x H x W tensor.
    x = torch.randn(1, 3, 16, 16, requires_grad=True)
    w = torch.randn(1, 441, 16, 16, requires_grad=True)
    out = gather(x, w, impl="fast")
    saved = out.grad_fn.saved_tensors  # type: ignore[union-attr]
    assert {t.data_ptr() for t in saved} == {x.data_ptr(), w.data_ptr()}


@pytest.mark.parametrize("which", [0, 1])
def test_partial_gradients_match_reference(which: int) -> None:
    # Only one input requires grad: the custom backward must skip the other and still be right.
    g = torch.Generator().manual_seed(11)
    v = torch.randn(2, 3, 2, 5, 6, generator=g, dtype=F64)
    w = torch.rand(2, 3, 25, 5, 6, generator=g, dtype=F64)
    up = torch.randn(2, 2, 5, 6, generator=g, dtype=F64)
    grads = []
    for impl in ("fast", "reference"):
        ins = [v.clone(), w.clone()]
        ins[which].requires_grad_()
        num, ws = splat(*ins, impl=impl, chunk=2)
        ((num * up).sum() + ws.square().sum()).backward()
        assert ins[1 - which].grad is None
        grads.append(ins[which].grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-12, atol=1e-12)


def test_float32_fast_close_to_float64_reference() -> None:
    # What the models run: float32 fast paths against the float64 references, K = 21.
    g = torch.Generator().manual_seed(12)
    x = torch.rand(1, 3, 24, 20, generator=g, dtype=F64)
    w = softmax_kernel(torch.randn(1, 441, 24, 20, generator=g, dtype=F64))
    torch.testing.assert_close(gather(x.float(), w.float()).double(), gather_reference(x, w), rtol=1e-5, atol=1e-6)
    v = torch.rand(1, 4, 3, 24, 20, generator=g, dtype=F64)
    lw = exp_kernel(torch.randn(1, 4, 441, 24, 20, generator=g, dtype=F64))
    ref = normalize_splat(*splat_reference(v, lw))
    fast = normalize_splat(*splat(v.float(), lw.float()))
    torch.testing.assert_close(fast.double(), ref, rtol=1e-5, atol=1e-6)
