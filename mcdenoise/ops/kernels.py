"""Turning network outputs into kernel weights, with the exponentials taken after a max shift."""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["softmax_kernel", "exp_kernel", "per_pixel_exp", "per_destination_exp", "SoftmaxKernel", "ExpKernel"]


def softmax_kernel(logits: Tensor, dim: int = -3) -> Tensor:
    """Normalised gather kernels (KPCN): softmax over the K*K taps.

    logits (B, K*K, H, W) (or any shape; ``dim`` is the tap dimension) -> same shape, summing to 1
    over ``dim``.  The per-pixel max is subtracted before ``exp`` (inside ``torch.softmax``), so
    large logits cannot overflow.
    """
    if not isinstance(logits, Tensor) or not logits.is_floating_point():
        raise TypeError("softmax_kernel: logits must be a floating-point tensor of shape (B, K*K, H, W)")
    return torch.softmax(logits, dim=dim)


def exp_kernel(log_weights: Tensor, dim: int | Sequence[int] | None = None) -> Tensor:
    """Unnormalised splat kernels predicted in log space (SBMC): ``exp(x - max)``.

    log_weights (B, S, K*K, H, W) (or (B, K*K, H, W)) -> same shape, positive.

    Which max is safe: the splat output at pixel q is normalised by the weight sum at q, which
    mixes the kernels of *different* samples and source pixels.  A shift therefore cancels only if
    it is the same for every kernel that reaches q, so the default ``dim=None`` takes one max per
    image (over all dims but the batch dim 0).  A per-kernel max (``dim=-3``) is only correct for
    kernels normalised on their own (gather); for splatting it changes the relative weights of
    samples.  With a per-image max, taps more than ~87 (float32) below the image max underflow to
    0; pixels all of whose incoming weights underflow come out as 0 after ``normalize_splat``.
    """
    if not isinstance(log_weights, Tensor) or not log_weights.is_floating_point() or log_weights.dim() < 2:
        raise TypeError("exp_kernel: log_weights must be a floating-point tensor of shape (B, S, K*K, H, W)")
    if dim is None:
        dims: tuple[int, ...] = tuple(range(1, log_weights.dim()))
    elif isinstance(dim, int):
        dims = (dim,)
    else:
        dims = tuple(dim)
    if not dims:
        return torch.ones_like(log_weights)
    # The shift cancels after normalisation, but gradients are taken through it anyway so that
    # exp_kernel is the exact derivative of what it returns.
    m = log_weights.amax(dim=dims, keepdim=True)
    return torch.exp(log_weights - m)


class SoftmaxKernel(nn.Module):
    """Module form of :func:`softmax_kernel`."""

    def __init__(self, dim: int = -3) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, logits: Tensor) -> Tensor:
        return softmax_kernel(logits, self.dim)


class ExpKernel(nn.Module):
    """Module form of :func:`exp_kernel` (per-image max by default)."""

    def __init__(self, dim: int | Sequence[int] | None = None) -> None:
        super().__init__()
        self.dim = dim

    def forward(self, log_weights: Tensor) -> Tensor:
        return exp_kernel(log_weights, self.dim)


def per_pixel_exp(logits: torch.Tensor) -> torch.Tensor:
    """Exponentiate gather-kernel logits ``(B, S, K*K, H, W)`` after subtracting, per output pixel,
    the max over its samples and taps.

    A gather output pixel is normalised by the sum of its own weights only, so any per-pixel
    constant cancels exactly and the largest weight of each pixel is 1 (no overflow/underflow).
    """
    m = logits.detach().amax(dim=(1, 2), keepdim=True)
    return torch.exp(logits - m)


def per_destination_exp(
    logits: torch.Tensor, kernel_size: int, source_max: torch.Tensor | None = None
) -> torch.Tensor:
    """Exponentiate splat-kernel logits ``(B, S, K*K, H, W)`` so that normalisation stays exact.

    A splat output pixel ``u`` is normalised by the sum of all weights that land on ``u``, coming
    from different samples at different pixels. Subtracting a per-sample max (as a softmax would)
    rescales samples against each other and changes the result; a single global max is exact but
    lets a dim region underflow next to a bright one. Here every tap is shifted by a constant that
    depends only on its destination pixel ``u``: ``c(u) = max`` of all logits of all samples within
    ``K x K`` of ``u``, an upper bound of every logit landing on ``u``. Tap ``t = (i, j)`` of a
    sample at ``x`` lands on ``u = x + (i - r, j - r)`` (flat index ``i*K + j``, ``r = K // 2``),
    the splat convention of :mod:`mcdenoise.ops.splat`. The shift is constant per destination and
    so cancels exactly in the per-pixel normalisation.

    ``source_max`` ``(B, 1, H, W)``, if given, replaces the per-pixel max over samples and taps of
    ``logits``: pass the max over *all* samples when ``logits`` holds only a chunk of them, so every
    chunk gets the same shift.
    """
    b, s, kk, h, w = logits.shape
    k = kernel_size
    if kk != k * k:
        raise ValueError(f"expected {k * k} kernel taps, got {kk}")
    r = k // 2
    with torch.no_grad():
        # (B, 1, H, W): max logit of each source pixel
        m = logits.amax(dim=(1, 2)).unsqueeze(1) if source_max is None else source_max.to(logits.dtype)
        c = F.max_pool2d(m, k, stride=1, padding=r)  # (B, 1, H, W): max over sources near u
        # Destination of tap (i, j) at x is x + (i - r, j - r): unfold gathers exactly that.
        # Replicate padding: taps landing outside the image are dropped by the splat anyway.
        cp = F.pad(c, (r, r, r, r), mode="replicate")
        shift = F.unfold(cp, k).reshape(b, 1, kk, h, w)
    return torch.exp(logits - shift)
