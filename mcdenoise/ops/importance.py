"""Importance-map kernels (WSKP, Fan et al. 2021, Eq. 2-5).

One scalar importance ``I`` per pixel encodes a whole kernel: for a window of size k around p,
``w_p(q) = exp(I(q)) / sum_{q' in win_k(p)} exp(I(q'))`` and the filtered image is
``out(p) = sum_{q in win_k(p)} w_p(q) c(q)``.  Windows are clipped at the border: only in-image q
take part (the paper unfolds the importance map; we do not let padding pixels carry weight).

Because the kernel at p depends only on exp(I) over p's window, ``out = box_k(exp(I) c) /
box_k(exp(I))``, and the box is separable: a pass along rows, then one along columns.

Numerics of the fast path (issue 8, bug 3): no differences of running sums (they cancel
catastrophically: one importance 40 above its row gave 0/0), no overflow, no 0/0, whatever the
range of I.  The exponentials are shifted by ONE constant per image and map, ``M = max I`` over
the image (detached: it cancels exactly in the ratio), so ``E = exp(I - M)`` in (0, 1] is computed
once per pixel, and numerator and denominator are plain clipped box sums of ``(E c, E)``.  Box
sums are direct: per axis, power-of-two partial sums ``S_2j(i) = S_j(i) + S_j(i + j)`` and one
slice of them per set bit of k (13 = 8 + 4 + 1), so every value is a sum of the window's own
terms, O(log k) additions per pixel.

Accuracy: a term keeps full relative precision as long as ``exp(I(q) - M)`` is a normal float.
If the window's own maximum is within ~58 of M (float32; ~470 in float64), the terms that fall
below the normal range are < 1e-10 of it and rounded with an absolute error < 2^-149 (< 1e-17 of
it), so the ratio is accurate to a few ulps plus the rounding of the exponent ``I(q) - M``: a
relative error of about eps |I(q) - M| / 2 per weight (up to ~30 eps for the weights that matter
in a window 58 below M in float32), i.e. the result is exact for I perturbed by eps max|I|,
the size of I's own float32 rounding.  Where the denominator is below
``tiny ** (2/3)`` (float32 ~e^-58, float64 ~e^-472) the window lies too far below the image
maximum, and those pixels take the exact per-window-shifted path instead (``_filter_exact``,
computed only on the rectangle around them, only when some pixel needs it, chosen with
``torch.where``; bad denominators are replaced by 1 before dividing, so no inf / NaN enters
the backward pass).  That path shifts every exponential by the maximum over the window it is
summed into (row pass by the row-segment maximum m1, column pass by ``exp(m1(q) - m2(p))``, m2
the window maximum): every exponent is <= 0 and the window maximum contributes exactly 1, so its
denominator is >= 1.  float16/bfloat16 inputs are accumulated in float32.

Cost per window size: one exponential per pixel of one channel, C multiplies, and about
2 (log2 k + popcount k) additions of C + 1 channels per pixel.  Without autograd on the CPU the
N filters and the fusion run band of rows by band of rows into preallocated buffers
(``_filter_banded``), so the intermediates stay in cache; with autograd (or on a GPU) the same
arithmetic runs on whole tensors (``_filter_one_shift``).  No K*K tensor either way.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mcdenoise.ops import importance_fast as _fast
from mcdenoise.ops._common import check_same, check_tensor, resolve_impl
from mcdenoise.ops.gather import gather_reference
from mcdenoise.ops.importance_fast import box_sum

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



def importance_filter_fast(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """Box sums of ``exp(I - M)`` (one shift per image) with the exact per-window-shifted path where
    they underflow; same contract as :func:`importance_filter` (see the module docstring)."""
    _check(image, importance, size, "importance_filter")
    if size == 1:
        return image.clone()
    if image.device.type == "cpu" and not _fast._needs_grad(image, importance):
        return _fast._filter_banded(image, importance, None, (size,))
    acc = _fast._acc_dtype(image)
    return _fast._filter_one_shift(image.to(acc), importance.to(acc), size).to(image.dtype)


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
    sizes = tuple(int(s) for s in sizes)
    for i, size in enumerate(sizes):
        _check(image, importance[:, i : i + 1], size, "importance_filter")
    if (
        resolve_impl(impl, "importance_filter") == "fast"
        and image.device.type == "cpu"
        and not _fast._needs_grad(image, importance, fusion_logits)
    ):
        # All N filters and the fusion in one pass over bands of rows (same arithmetic as below).
        return _fast._filter_banded(image, importance, fusion_logits, sizes)
    fusion = torch.softmax(fusion_logits, dim=1)
    out = None
    for i, size in enumerate(sizes):
        filtered = importance_filter(image, importance[:, i : i + 1], size, impl=impl)
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
