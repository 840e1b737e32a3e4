"""Triton GPU kernels (forward only, inference) for gather, splat and the importance filter.

Explicit opt-in: nothing in ``mcdenoise.ops`` imports this module and no ``impl="auto"`` path
uses it.  Each function has the contract of the op's plain-PyTorch reference (the spec):

* :func:`gather_triton` = :func:`mcdenoise.ops.gather.gather_reference`
* :func:`splat_triton` = :func:`mcdenoise.ops.splat.splat_reference` (``(num, wsum)``)
* :func:`importance_filter_triton` = :func:`mcdenoise.ops.importance.importance_filter_reference`

Conventions as everywhere in ``mcdenoise.ops``: tap ``i * K + j`` has offset ``(i - r, j - r)``,
``r = K // 2``, zero outside the image.  Accumulation is in float32 (float64 for float64 inputs);
the result has the input dtype.  No autograd: inputs that require a gradient are refused.

Layout: one program per (block of ``BLOCK_P`` flat pixels, batch item, block of channels); the
program holds a (channels x pixels) float32 accumulator in registers and loops over the K*K taps,
loading each tap's weight once for all channels of the block.  Inputs are made contiguous.

Splat is written in *gather form*: output pixel p sums, over samples s and taps t, the
contribution of the source pixel ``q = p - d_t`` (``w[s, t, q] * v[s, :, q]``).  Every output is
written by exactly one program, so no ``tl.atomic_add`` is needed: the result is deterministic
(float atomics would make the summation order, hence the last bits, vary run to run), there is no
atomic contention on the K*K*S updates per pixel, and the weight sum comes out of the same loop.
Each weight is still read once per channel block; the values are re-read K*K times (from cache).

Importance filter: ``out(p) = sum_q exp(I(q) - m(p)) c(q) / sum_q exp(I(q) - m(p))`` over the
in-image part of p's k x k window, with ``m(p)`` the maximum of I over that same window (a first
pass over the window).  Every exponent is <= 0 and the window's own maximum contributes
``exp(0) = 1``, so nothing overflows and the denominator is >= 1 whatever the range of I (no 0/0).
Direct k*k taps per pixel (no separable box sums): 2 k^2 importance loads per pixel.

Status: verified only in Triton's CPU interpreter (``TRITON_INTERPRET=1``, tests/test_ops_triton.py);
never compiled, run or timed on a GPU.  ``TRITON_INTERPRET`` must be set before this module is
first imported (``triton.jit`` reads it when the kernels are defined).
"""

from __future__ import annotations

import torch
from torch import Tensor

from mcdenoise.ops.gather import _check as _check_gather
from mcdenoise.ops.importance import _check as _check_importance
from mcdenoise.ops.splat import _check as _check_splat

try:  # Optional dependency: `pip install mcdenoise[triton]`.
    import triton
    import triton.language as tl
except ImportError:  # pragma: no cover - exercised only where triton is missing
    triton = None
    tl = None

__all__ = [
    "HAVE_TRITON",
    "kernels_interpreted",
    "gather_triton",
    "splat_triton",
    "importance_filter_triton",
]

HAVE_TRITON = triton is not None

# Pixels per program and the largest channel block (both powers of two, as tl.arange needs).
_BLOCK_P = 128
_MAX_BLOCK_C = 16


if HAVE_TRITON:

    @triton.jit
    def _gather_kernel(x_ptr, w_ptr, out_ptr, C, H, W, K, ACC: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_P: tl.constexpr):
        pid_p = tl.program_id(0)
        b = tl.program_id(1).to(tl.int64)
        pid_c = tl.program_id(2)
        hw = H * W
        r = K // 2
        p = pid_p * BLOCK_P + tl.arange(0, BLOCK_P)
        c = pid_c * BLOCK_C + tl.arange(0, BLOCK_C)
        pmask = p < hw
        cmask = c < C
        y = p // W
        x = p % W
        x_base = x_ptr + b * C * hw
        w_tap = w_ptr + b * K * K * hw  # advanced by one H*W plane per tap (64-bit pointer arithmetic)
        acc = tl.zeros((BLOCK_C, BLOCK_P), dtype=ACC)
        for t in range(K * K):
            yy = y + (t // K - r)
            xx = x + (t % K - r)
            inside = pmask & (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
            wt = tl.load(w_tap + p, mask=pmask, other=0.0).to(ACC)
            q = yy * W + xx
            v = tl.load(x_base + c[:, None] * hw + q[None, :], mask=cmask[:, None] & inside[None, :], other=0.0)
            acc += v.to(ACC) * wt[None, :]
            w_tap += hw
        out = out_ptr + b * C * hw + c[:, None] * hw + p[None, :]
        tl.store(out, acc.to(out_ptr.dtype.element_ty), mask=cmask[:, None] & pmask[None, :])

    @triton.jit
    def _splat_kernel(
        v_ptr, w_ptr, num_ptr, wsum_ptr, S, C, H, W, K, ACC: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_P: tl.constexpr
    ):
        pid_p = tl.program_id(0)
        b = tl.program_id(1).to(tl.int64)
        pid_c = tl.program_id(2)
        hw = H * W
        r = K // 2
        p = pid_p * BLOCK_P + tl.arange(0, BLOCK_P)
        c = pid_c * BLOCK_C + tl.arange(0, BLOCK_C)
        pmask = p < hw
        cmask = c < C
        y = p // W
        x = p % W
        acc = tl.zeros((BLOCK_C, BLOCK_P), dtype=ACC)
        wacc = tl.zeros((BLOCK_P,), dtype=ACC)
        for s in range(S):
            bs = b * S + s
            v_base = v_ptr + bs * C * hw
            w_tap = w_ptr + bs * K * K * hw
            for t in range(K * K):
                # Tap t of the source pixel q = p - d lands on p.
                ys = y - (t // K - r)
                xs = x - (t % K - r)
                inside = pmask & (ys >= 0) & (ys < H) & (xs >= 0) & (xs < W)
                q = ys * W + xs
                wt = tl.load(w_tap + q, mask=inside, other=0.0).to(ACC)
                v = tl.load(v_base + c[:, None] * hw + q[None, :], mask=cmask[:, None] & inside[None, :], other=0.0)
                acc += v.to(ACC) * wt[None, :]
                wacc += wt
                w_tap += hw
        num = num_ptr + b * C * hw + c[:, None] * hw + p[None, :]
        tl.store(num, acc.to(num_ptr.dtype.element_ty), mask=cmask[:, None] & pmask[None, :])
        # Every channel block computes the weight sum; the first one writes it.
        if pid_c == 0:
            tl.store(wsum_ptr + b * hw + p, wacc.to(wsum_ptr.dtype.element_ty), mask=pmask)

    @triton.jit
    def _importance_kernel(x_ptr, i_ptr, out_ptr, C, H, W, K, ACC: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_P: tl.constexpr):
        pid_p = tl.program_id(0)
        b = tl.program_id(1).to(tl.int64)
        pid_c = tl.program_id(2)
        hw = H * W
        r = K // 2
        p = pid_p * BLOCK_P + tl.arange(0, BLOCK_P)
        c = pid_c * BLOCK_C + tl.arange(0, BLOCK_C)
        pmask = p < hw
        cmask = c < C
        y = p // W
        x = p % W
        i_base = i_ptr + b * hw
        x_base = x_ptr + b * C * hw
        # Pass 1: m(p) = max of I over the in-image part of p's window (finite: the centre is inside).
        m = tl.full((BLOCK_P,), float("-inf"), dtype=ACC)
        for t in range(K * K):
            yy = y + (t // K - r)
            xx = x + (t % K - r)
            inside = pmask & (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
            lw = tl.load(i_base + yy * W + xx, mask=inside, other=float("-inf")).to(ACC)
            m = tl.maximum(m, lw)
        m = tl.where(pmask, m, 0.0)
        # Pass 2: exp(I(q) - m(p)) <= 1; the window maximum contributes 1, so den >= 1.
        num = tl.zeros((BLOCK_C, BLOCK_P), dtype=ACC)
        den = tl.zeros((BLOCK_P,), dtype=ACC)
        for t in range(K * K):
            yy = y + (t // K - r)
            xx = x + (t % K - r)
            inside = pmask & (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
            q = yy * W + xx
            # Outside taps read -inf: exp(-inf - m) = 0, no overflow in the masked lanes.
            lw = tl.load(i_base + q, mask=inside, other=float("-inf")).to(ACC)
            e = tl.where(inside, tl.exp(lw - m), 0.0)
            v = tl.load(x_base + c[:, None] * hw + q[None, :], mask=cmask[:, None] & inside[None, :], other=0.0)
            num += v.to(ACC) * e[None, :]
            den += e
        den = tl.where(pmask, den, 1.0)
        out = out_ptr + b * C * hw + c[:, None] * hw + p[None, :]
        tl.store(out, (num / den[None, :]).to(out_ptr.dtype.element_ty), mask=cmask[:, None] & pmask[None, :])


def kernels_interpreted() -> bool:
    """Whether the kernels were built for Triton's CPU interpreter (``TRITON_INTERPRET=1`` at import)."""
    if not HAVE_TRITON:
        return False
    from triton.runtime.interpreter import InterpretedFunction

    return isinstance(_gather_kernel, InterpretedFunction)


def _prepare(op: str, *tensors: Tensor) -> None:
    """Raise unless triton is installed, the tensors can reach a kernel and need no gradient."""
    if not HAVE_TRITON:
        raise ImportError(f"{op}: needs the optional dependency triton (pip install 'mcdenoise[triton]')")
    dev = tensors[0].device
    if dev.type != "cuda" and not kernels_interpreted():
        raise ValueError(
            f"{op}: tensors must be on a CUDA device, got {dev} (CPU tensors run only in Triton's "
            "interpreter: set TRITON_INTERPRET=1 before importing mcdenoise.ops.triton_kernels)"
        )
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        raise RuntimeError(f"{op} is forward-only (inference); use the ops in mcdenoise.ops where gradients are needed")


def _acc(dtype: torch.dtype):
    # float32 accumulation for half, bfloat16 and float32 inputs; float64 stays float64.
    return tl.float64 if dtype == torch.float64 else tl.float32


def _grid(b: int, c: int, hw: int) -> tuple[tuple[int, int, int], int]:
    block_c = min(_MAX_BLOCK_C, triton.next_power_of_2(max(c, 1)))
    # At least one channel block, so that splat with C = 0 still writes its weight sum.
    return (triton.cdiv(hw, _BLOCK_P), b, max(1, triton.cdiv(c, block_c))), block_c


def gather_triton(image: Tensor, weights: Tensor) -> Tensor:
    """Per-pixel K x K gather, forward only: image (B, C, H, W), weights (B, K*K, H, W) -> (B, C, H, W).

    ``out[b,c,y,x] = sum_ij w[b,ij,y,x] * image[b,c,y+dy,x+dx]``, zero outside the image; same
    contract as :func:`mcdenoise.ops.gather.gather_reference`.
    """
    k = _check_gather(image, weights, "gather_triton")
    _prepare("gather_triton", image, weights)
    b, c, h, w = image.shape
    out = torch.empty_like(image, memory_format=torch.contiguous_format)
    if out.numel() == 0:
        return out
    grid, block_c = _grid(b, c, h * w)
    _gather_kernel[grid](
        image.contiguous(), weights.contiguous(), out, c, h, w, k,
        ACC=_acc(image.dtype), BLOCK_C=block_c, BLOCK_P=_BLOCK_P,
    )
    return out


def splat_triton(values: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Per-sample K x K splat, forward only: values (B, S, C, H, W), weights (B, S, K*K, H, W) ->
    ``(numerator (B, C, H, W), weight_sum (B, 1, H, W))``; contributions outside the image dropped.

    Same contract as :func:`mcdenoise.ops.splat.splat_reference`; normalise with
    :func:`mcdenoise.ops.splat.normalize_splat`.  Gather form, no atomics (see the module docstring).
    """
    k = _check_splat(values, weights, "splat_triton")
    _prepare("splat_triton", values, weights)
    b, s, c, h, w = values.shape
    num = values.new_empty((b, c, h, w))
    wsum = values.new_empty((b, 1, h, w))
    if b * h * w == 0:
        return num, wsum
    grid, block_c = _grid(b, c, h * w)
    _splat_kernel[grid](
        values.contiguous(), weights.contiguous(), num, wsum, s, c, h, w, k,
        ACC=_acc(values.dtype), BLOCK_C=block_c, BLOCK_P=_BLOCK_P,
    )
    return num, wsum


def importance_filter_triton(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """WSKP importance filter (one map), forward only: image (B, C, H, W), importance (B, 1, H, W),
    odd window ``size`` -> (B, C, H, W).

    ``out(p) = sum_q exp(I(q)) c(q) / sum_q exp(I(q))`` over the k x k window around p clipped to
    the image; each window shifted by its own maximum (no overflow, no 0/0 for any range of I).
    Same contract as :func:`mcdenoise.ops.importance.importance_filter_reference`.
    """
    _check_importance(image, importance, size, "importance_filter_triton")
    _prepare("importance_filter_triton", image, importance)
    b, c, h, w = image.shape
    out = torch.empty_like(image, memory_format=torch.contiguous_format)
    if out.numel() == 0:
        return out
    grid, block_c = _grid(b, c, h * w)
    _importance_kernel[grid](
        image.contiguous(), importance.contiguous(), out, c, h, w, size,
        ACC=_acc(image.dtype), BLOCK_C=block_c, BLOCK_P=_BLOCK_P,
    )
    return out
