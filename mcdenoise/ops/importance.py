"""Importance-map kernels (WSKP, Fan et al. 2021, Eq. 2-5).

One scalar importance ``I`` per pixel encodes a whole kernel: for a window of size k around p,
``w_p(q) = exp(I(q)) / sum_{q' in win_k(p)} exp(I(q'))`` and the filtered image is
``out(p) = sum_{q in win_k(p)} w_p(q) c(q)``.  Windows are clipped at the border: only in-image q
take part (the paper unfolds the importance map; we do not let padding pixels carry weight).

Because the kernel at p depends only on exp(I) over p's window, ``out = box_k(exp(I) c) /
box_k(exp(I))``: two box sums, each O(H W) whatever k, computed with separable cumulative sums.

Memory / numerics of the fast path: ``exp(I - max_image I)`` and the box sums are formed in
float64 (float32 inputs included, except on devices without float64): this keeps the cumulative
sums exact to ~1e-12 relative and lets I span ~700 within one image before windows underflow;
windows whose every importance lies > 700 below the image max are treated as uniform.  Extra
memory: a few ``8 B (C + 1) H W``-byte buffers per window size; no K*K tensor is formed.
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

# Shifted log-importances below this are clamped (float64 exp underflows near -745).
_MIN_LOG = -700.0


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


def box_sum(x: Tensor, size: int) -> Tensor:
    """Sum over the size x size window around each pixel, clipped at the border: (..., H, W) -> same.

    Separable cumulative sums (one per axis), so the cost is O(H W) whatever ``size`` is and the
    running sums stay short (one row or column), which keeps cancellation error small.
    """
    r = size // 2
    if r == 0:
        return x.clone()
    for axis in (-1, -2):
        n = x.shape[axis]
        c = torch.cumsum(x, dim=axis)  # c[t] = sum of x[:t+1]
        # Window [t - r, t + r] clipped to [0, n): c[min(t + r, n - 1)] - c[t - r - 1] (0 below 0).
        # Extending c with r copies of its last entry and r + 1 zeros in front turns both clamps
        # into two plain slices of one tensor.
        lead = list(c.shape)
        lead[axis] = r + 1
        tail = c.narrow(axis, n - 1, 1).expand(*[r if d == (axis % c.dim()) else -1 for d in range(c.dim())])
        ext = torch.cat([c.new_zeros(lead), c, tail], dim=axis)  # ext[t + r + 1] = c[t]
        x = ext.narrow(axis, 2 * r + 1, n) - ext.narrow(axis, 0, n)
    return x


def _acc_dtype(t: Tensor) -> torch.dtype:
    if t.dtype == torch.float64 or t.device.type == "mps":
        return t.dtype if t.dtype == torch.float64 else torch.float32
    return torch.float64


def importance_filter_fast(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """Ratio-of-box-sums importance filter; same contract as :func:`importance_filter`."""
    _check(image, importance, size, "importance_filter")
    if size == 1:
        return image.clone()
    acc = _acc_dtype(image)
    imp = importance.to(acc)
    # Any per-image shift cancels in the ratio, so the max carries no gradient: detach is exact.
    m = imp.amax(dim=(1, 2, 3), keepdim=True).detach()
    e = torch.exp((imp - m).clamp(min=_MIN_LOG))  # (B, 1, H, W)
    c = image.shape[1]
    sums = box_sum(torch.cat([e * image.to(acc), e], dim=1), size)  # numerator and denominator in one pass
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
