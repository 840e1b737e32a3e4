"""Importance-map kernels (WSKP, Fan et al. 2021, Eq. 2-5).

One scalar importance ``I`` per pixel encodes a whole kernel: for a window of size k around p,
``w_p(q) = exp(I(q)) / sum_{q' in win_k(p)} exp(I(q'))`` and the filtered image is
``out(p) = sum_{q in win_k(p)} w_p(q) c(q)``.  Windows are clipped at the border: only in-image q
take part (the paper unfolds the importance map; we do not let padding pixels carry weight).

Because the kernel at p depends only on exp(I) over p's window, ``out = box_k(exp(I) c) /
box_k(exp(I))``, and the box is separable: a pass along rows, then one along columns.

Numerics of the fast path (issue 8, bug 3): every exponential is shifted by the maximum over the
window it is summed into, never by an image-wide maximum, and the sums are direct sums of k
shifted slices, never differences of running sums (which cancel catastrophically: one importance
40 above its row gave 0/0).  The row pass sums ``exp(I(q) - m1(p))`` with m1 the row-segment
maximum; the column pass carries each row sum with its own m1 and sums ``exp(m1(q) - m2(p))``
times it, m2 the maximum over the whole window.  Every exponent is <= 0 and the window's own
maximum contributes exactly 1, so the denominator is >= 1: no overflow, no 0/0, whatever the
range of I, and float32 accumulation is accurate to a few ulps (float16/bfloat16 inputs are
accumulated in float32).  The shifts cancel exactly, so they are detached.  Cost per window size:
2k exponentials of one channel and 2k multiply-adds of C + 1 channels per pixel; extra memory a
few ``(C + 1) H W`` buffers (no K*K tensor).
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mcdenoise.ops._common import check_same, check_tensor, resolve_impl
from mcdenoise.ops.gather import gather_reference

__all__ = [
    "importance_filter",
    "importance_filter_reference",
    "importance_filter_fast",
    "importance_kernel_reference",
    "box_sum",
    "fused_importance_filter",
    "ImportanceFilter",
    "FusedImportanceFilter",
    "WSKP_SIZES",
]

WSKP_SIZES: tuple[int, ...] = (3, 5, 7, 9, 11, 13)

_IMG = "(B, C, H, W)"
_IMP = "(B, 1, H, W)"

def _check(image: Tensor, importance: Tensor, size: int, op: str) -> None:
    check_tensor(image, "image", 4, _IMG, op)
    check_tensor(importance, "importance", 4, _IMP, op)
    check_same(image, importance, "image and importance", op)
    b, _, h, w = image.shape
    if importance.shape != (b, 1, h, w):
        raise ValueError(
            f"{op}: importance must have shape {_IMP} = ({b}, 1, {h}, {w}) to match image "
            f"{tuple(image.shape)}, got {tuple(importance.shape)}"
        )
    if not isinstance(size, int) or size < 1 or size % 2 == 0:
        raise ValueError(f"{op}: size must be a positive odd int, got {size!r}")


def importance_kernel_reference(importance: Tensor, size: int) -> Tensor:
    """Explicit kernels: importance (B,1,H,W) -> (B, size*size, H, W), softmax over in-image taps."""
    b, _, h, w = importance.shape
    r = size // 2
    unf = F.unfold(importance, kernel_size=size, padding=r).reshape(b, size * size, h, w)
    inside = F.unfold(torch.ones_like(importance[:1]), kernel_size=size, padding=r).reshape(1, size * size, h, w) > 0
    logits = unf.masked_fill(~inside, float("-inf"))
    return torch.softmax(logits, dim=1)


def importance_filter_reference(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """Unfold + softmax + gather, written for clarity: (B,C,H,W), (B,1,H,W) -> (B,C,H,W)."""
    _check(image, importance, size, "importance_filter_reference")
    return gather_reference(image, importance_kernel_reference(importance, size))


def _tap_slices(x: Tensor, size: int, axis: int, pad_value: float) -> list[Tensor]:
    """Pad ``x`` by size // 2 on both ends of ``axis`` and return the k slices, one per window tap."""
    r = size // 2
    n = x.shape[axis]
    pad = [0, 0, 0, 0]
    pad[0 if axis == -1 else 2] = r
    pad[1 if axis == -1 else 3] = r
    xp = F.pad(x, pad, value=pad_value)
    return [xp.narrow(axis, t, n) for t in range(size)]


def box_sum(x: Tensor, size: int) -> Tensor:
    """Sum over the size x size window around each pixel, clipped at the border: (..., H, W) -> same.

    Separable direct sums of shifted slices of a zero-padded copy (no running-sum differences, so
    no cancellation); cost O(size H W).
    """
    if size < 1 or size % 2 == 0:
        raise ValueError(f"box_sum: size must be a positive odd int, got {size!r}")
    lead = x.shape[:-2]
    y = x.reshape(-1, 1, *x.shape[-2:])
    for axis in (-1, -2):
        y = torch.stack(_tap_slices(y, size, axis, 0.0)).sum(0) if size > 1 else y.clone()
    return y.reshape(*lead, *x.shape[-2:])


def _shifted_window_sum(values: Tensor, log_w: Tensor, size: int, axis: int) -> tuple[Tensor, Tensor]:
    """One separable pass of the importance filter along ``axis`` (-1 rows, -2 columns).

    Args:
        values: (B, C, H, W) values v.
        log_w: (B, 1, H, W) log-weights l (finite).
        size: odd window length along ``axis``.

    Returns:
        ``(sums, shift)``: ``sums(p) = sum_{q in win(p)} exp(l(q) - shift(p)) v(q)``, (B, C, H, W),
        with ``shift(p) = max_{q in win(p)} l(q)`` (B, 1, H, W), detached.  Taps outside the image
        are padded with l = -inf, v = 0, so they carry no weight.
    """
    r = size // 2
    kernel = (1, size) if axis == -1 else (size, 1)
    padding = (0, r) if axis == -1 else (r, 0)
    # The shift cancels in the final ratio, so it carries no gradient: detach is exact.
    shift = F.max_pool2d(log_w.detach(), kernel, stride=1, padding=padding)
    lw_taps = _tap_slices(log_w, size, axis, float("-inf"))
    v_taps = _tap_slices(values, size, axis, 0.0)
    # In-place accumulation halves the CPU time; autograd allows it (addcmul_ saves its factors,
    # not the accumulator).
    acc = torch.zeros_like(values)
    for lw, v in zip(lw_taps, v_taps):
        acc.addcmul_(torch.sub(lw, shift).exp_(), v)
    return acc, shift


def _acc_dtype(t: Tensor) -> torch.dtype:
    # Half-precision sums of up to 169 terms would lose ~2 digits; float32 is enough (see above).
    return torch.float32 if t.dtype in (torch.float16, torch.bfloat16) else t.dtype


def importance_filter_fast(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """Two-pass, per-window-shifted importance filter; same contract as :func:`importance_filter`."""
    _check(image, importance, size, "importance_filter")
    if size == 1:
        return image.clone()
    acc = _acc_dtype(image)
    c = image.shape[1]
    # Numerator and denominator in one pass: the image with a ones channel.
    vals = torch.cat([image.to(acc), torch.ones_like(importance, dtype=acc)], dim=1)
    rows, m1 = _shifted_window_sum(vals, importance.to(acc), size, -1)  # row sums relative to m1
    sums, _ = _shifted_window_sum(rows, m1, size, -2)  # relative to the window max; denominator >= 1
    return (sums[:, :c] / sums[:, c:]).to(image.dtype)


def importance_filter(image: Tensor, importance: Tensor, size: int, *, impl: str = "auto") -> Tensor:
    """Filter with kernels decoded from one importance map (WSKP Eq. 2-4).

    Args:
        image: (B, C, H, W).
        importance: (B, 1, H, W) log-importance I.
        size: odd window size k.
        impl: "auto" | "reference" | "fast".

    Returns:
        (B, C, H, W): ``sum_{q in win(p)} exp(I(q)) c(q) / sum_{q in win(p)} exp(I(q))``, windows
        clipped to the image.
    """
    if resolve_impl(impl, "importance_filter") == "reference":
        return importance_filter_reference(image, importance, size)
    return importance_filter_fast(image, importance, size)


def fused_importance_filter(
    image: Tensor,
    importance: Tensor,
    fusion_logits: Tensor,
    sizes: Sequence[int] = WSKP_SIZES,
    *,
    impl: str = "auto",
) -> Tensor:
    """WSKP Eq. 5: per-pixel softmax-weighted sum of N importance filters of different sizes.

    Args:
        image: (B, C, H, W).
        importance: (B, N, H, W), map n filters with window ``sizes[n]``.
        fusion_logits: (B, N, H, W), softmax over N gives the fusion weights.
        sizes: N odd window sizes (default 3, 5, ..., 13).

    Returns:
        (B, C, H, W).
    """
    op = "fused_importance_filter"
    check_tensor(image, "image", 4, _IMG, op)
    n = len(sizes)
    if n == 0:
        raise ValueError(f"{op}: sizes must name at least one window size")
    doc = f"(B, N={n}, H, W)"
    check_tensor(importance, "importance", 4, doc, op)
    check_tensor(fusion_logits, "fusion_logits", 4, doc, op)
    b, _, h, w = image.shape
    for name, t in (("importance", importance), ("fusion_logits", fusion_logits)):
        if t.shape != (b, n, h, w):
            raise ValueError(f"{op}: {name} must have shape {doc} = ({b}, {n}, {h}, {w}), got {tuple(t.shape)}")
    fusion = torch.softmax(fusion_logits, dim=1)
    out = None
    for i, size in enumerate(sizes):
        filtered = importance_filter(image, importance[:, i : i + 1], int(size), impl=impl)
        term = fusion[:, i : i + 1] * filtered
        out = term if out is None else out + term
    return out  # type: ignore[return-value]


class ImportanceFilter(nn.Module):
    """Module form of :func:`importance_filter` for one window size."""

    def __init__(self, size: int, impl: str = "auto") -> None:
        super().__init__()
        self.size, self.impl = size, impl

    def forward(self, image: Tensor, importance: Tensor) -> Tensor:
        return importance_filter(image, importance, self.size, impl=self.impl)


class FusedImportanceFilter(nn.Module):
    """Module form of :func:`fused_importance_filter`."""

    def __init__(self, sizes: Sequence[int] = WSKP_SIZES, impl: str = "auto") -> None:
        super().__init__()
        self.sizes, self.impl = tuple(int(s) for s in sizes), impl

    def forward(self, image: Tensor, importance: Tensor, fusion_logits: Tensor) -> Tensor:
        return fused_importance_filter(image, importance, fusion_logits, self.sizes, impl=self.impl)
