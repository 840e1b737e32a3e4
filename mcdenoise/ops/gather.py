"""Per-pixel kernel gather (KPCN, PixelGather, per-layer filtering).

``out[b, c, y, x] = sum_ij w[b, ij, y, x] * image[b, c, y + dy, x + dx]`` with ``(dy, dx) =
(i - r, j - r)`` for flat tap ``i * K + j``, ``r = K // 2``, zero padding outside the image.
One kernel per pixel, shared by all channels; weights are used as given (normalise them first,
e.g. with :func:`mcdenoise.ops.kernels.softmax_kernel`).

Memory (float32, B images of C x H x W, K x K kernels):
* reference: the unfold, ``4 B C K^2 H W`` bytes (1.6 GB for one 3-channel 512^2 image at K = 21),
  kept by autograd for backward.
* fast: one zero-padded image copy, ``4 B C (H + 2r)(W + 2r)`` bytes, plus the output; backward
  keeps only the inputs.  Time is K^2 shifted multiply-adds over the image.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from mcdenoise.ops._common import check_same, check_tensor, kernel_size_from, resolve_impl
from mcdenoise.ops._shift import GatherFn

__all__ = ["gather", "gather_reference", "gather_fast", "gather_rows", "Gather"]

_IMG = "(B, C, H, W)"
_W = "(B, K*K, H, W)"


def _check(image: Tensor, weights: Tensor, op: str) -> int:
    check_tensor(image, "image", 4, _IMG, op)
    check_tensor(weights, "weights", 4, _W, op)
    check_same(image, weights, "image and weights", op)
    b, _, h, w = image.shape
    if weights.shape[0] != b or weights.shape[-2:] != image.shape[-2:]:
        raise ValueError(
            f"{op}: weights must have shape {_W} = ({b}, K*K, {h}, {w}) to match image {tuple(image.shape)}, "
            f"got {tuple(weights.shape)}"
        )
    return kernel_size_from(weights.shape[1], "weights", _W, op)


def gather_reference(image: Tensor, weights: Tensor) -> Tensor:
    """Unfold-based gather, written for clarity: image (B,C,H,W), weights (B,K*K,H,W) -> (B,C,H,W).

    Materialises the (B, C, K*K, H, W) neighbourhood tensor.
    """
    k = _check(image, weights, "gather_reference")
    b, c, h, w = image.shape
    # unfold's channel index is c * K*K + i * K + j with tap (i, j) reading pixel p + (i - r, j - r).
    patches = F.unfold(image.reshape(b * c, 1, h, w), kernel_size=k, padding=k // 2)
    patches = patches.reshape(b, c, k * k, h, w)
    return (patches * weights.unsqueeze(1)).sum(dim=2)


def gather_fast(image: Tensor, weights: Tensor) -> Tensor:
    """Shift-and-accumulate gather with an adjoint backward; same contract as :func:`gather`."""
    k = _check(image, weights, "gather")
    return GatherFn.apply(image, weights, k)


def gather_rows(image: Tensor, weights: Tensor, row0: int) -> Tensor:
    """Gather for a band of output rows only: image (B, C, H, W) whole, weights (B, K*K, h, W)
    for output rows ``row0 .. row0 + h - 1`` -> (B, C, h, W), equal to those rows of
    ``gather(image, full_weights)`` (zero outside the image). Reads only image rows
    ``row0 - r .. row0 + h - 1 + r``, so a model can build kernels one row band at a time.
    Plain PyTorch ops (differentiable through autograd, but meant for inference).
    """
    check_tensor(image, "image", 4, _IMG, "gather_rows")
    check_tensor(weights, "weights", 4, _W, "gather_rows")
    k = kernel_size_from(weights.shape[1], "weights", _W, "gather_rows")
    r = k // 2
    b, c, hh, w = image.shape
    h = weights.shape[2]
    if weights.shape[0] != b or weights.shape[3] != w or row0 < 0 or row0 + h > hh:
        raise ValueError(f"gather_rows: weights {tuple(weights.shape)} for rows {row0}.. do not fit image {tuple(image.shape)}")
    lo, hi = row0 - r, row0 + h + r
    rows = image[:, :, max(lo, 0) : min(hi, hh)]
    # Zero rows stand in for the image outside its top and bottom, zero columns for the sides.
    xp = F.pad(rows, (r, r, max(0, -lo), max(0, hi - hh)))
    out = image.new_zeros((b, c, h, w))
    for i in range(k):
        for j in range(k):
            t = i * k + j
            out.addcmul_(xp[:, :, i : i + h, j : j + w], weights[:, t : t + 1])
    return out


def gather(image: Tensor, weights: Tensor, *, impl: str = "auto") -> Tensor:
    """Filter each pixel with its own K x K kernel, shared across channels.

    Args:
        image: (B, C, H, W).
        weights: (B, K*K, H, W), K odd, tap ``i * K + j`` at offset ``(i - K//2, j - K//2)``.
            Used as given (no normalisation).
        impl: "auto" | "reference" | "fast".

    Returns:
        (B, C, H, W): ``out[b,c,y,x] = sum_ij w[b,ij,y,x] * image[b,c,y+dy,x+dx]``, zero outside.
    """
    if resolve_impl(impl, "gather") == "reference":
        return gather_reference(image, weights)
    return gather_fast(image, weights)


class Gather(nn.Module):
    """Module form of :func:`gather`: ``forward(image (B,C,H,W), weights (B,K*K,H,W)) -> (B,C,H,W)``."""

    def __init__(self, impl: str = "auto") -> None:
        super().__init__()
        self.impl = impl

    def forward(self, image: Tensor, weights: Tensor) -> Tensor:
        return gather(image, weights, impl=self.impl)
