"""Turning network outputs into kernel weights, with the exponentials taken after a max shift."""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "softmax_kernel",
    "exp_kernel",
    "per_pixel_exp",
    "per_destination_exp",
    "destination_max",
    "SoftmaxKernel",
    "ExpKernel",
]


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


def _inside_mask(k: int, height: int, width: int, row0: int, rows: int, device: torch.device) -> Tensor:
    """(K*K, rows, width) bool: does tap ``i*K + j`` of pixel ``(row0 + y, x)`` read inside the
    ``height x width`` image (offset ``(i - r, j - r)``)?"""
    r = k // 2
    d = torch.arange(k, device=device) - r
    ys = torch.arange(row0, row0 + rows, device=device)
    xs = torch.arange(width, device=device)
    vy = ((ys[None] + d[:, None]) >= 0) & ((ys[None] + d[:, None]) < height)  # (K, rows)
    vx = ((xs[None] + d[:, None]) >= 0) & ((xs[None] + d[:, None]) < width)  # (K, W)
    return (vy[:, None, :, None] & vx[None, :, None, :]).reshape(k * k, rows, width)


def per_pixel_exp(
    logits: Tensor, *, row0: int = 0, height: int | None = None, inplace: bool = False
) -> Tensor:
    """Exponentiate gather-kernel logits ``(B, S, K*K, H, W)`` after subtracting, per output pixel,
    the max over its samples and over the taps that read *inside* the image.

    A gather output pixel is normalised by the sum of its own in-image weights only, so any
    per-pixel constant cancels exactly; with the max taken over in-image taps, the largest weight
    that counts is exactly 1, so the weight sum is >= 1 and an ``eps`` of 1e-8 cannot dominate it
    however peaked the kernel is. Taps reading outside the image (zero padding: they contribute
    nothing to any gather) get weight exactly 0, so they can neither hold the max nor overflow.

    ``row0``/``height``: when ``logits`` covers only image rows ``row0 .. row0 + H - 1`` of an
    image ``height`` rows high (row bands), the in-image test uses the full image's rows.
    ``inplace``: overwrite ``logits`` (allowed under autograd when nothing saved it, e.g. the raw
    output of a convolution) instead of allocating a second kernel-sized tensor.
    """
    b, s, kk, h, w = logits.shape
    k = int(round(kk**0.5))
    if k * k != kk or k % 2 != 1:
        raise ValueError(f"per_pixel_exp: expected K*K taps with K odd, got {kk}")
    inside = _inside_mask(k, h if height is None else height, w, row0, h, logits.device)
    with torch.no_grad():
        m = logits.amax(dim=1).masked_fill(~inside, float("-inf")).amax(dim=1)  # (B, H, W)
    out = logits.sub_(m[:, None, None]) if inplace else logits - m[:, None, None]
    # -inf before exp, not 0 after: exp_ saves its result for backward, so it must be the last write.
    out.masked_fill_(~inside, float("-inf"))
    return out.exp_()


def destination_max(
    logits: Tensor, kernel_size: int, *, plane: Tensor | None = None, row0: int = 0
) -> Tensor:
    """Max logit *landing* on every destination pixel of a splat, on a padded plane.

    logits ``(B, S, K*K, h, W)`` -> plane ``(B, H + 2r, W + 2r)`` (``r = K // 2``; with ``plane``
    None, ``H = h``), where ``plane[b, u + r]`` is the max over samples ``s`` and taps ``t`` of
    ``logits[b, s, t, x]`` over all sources ``x = u - d_t`` (``d_t = (i - r, j - r)`` for tap
    ``t = i * K + j``): exactly the taps that land on ``u``. The border ring holds the max of the
    taps landing just outside the image (dropped by the splat, but they need a bound too).

    Per tap this is the max over samples moved by the tap's offset, then a max over taps: K*K
    shifted maxima over ``(B, h, W)``, no kernel-sized temporary beyond ``logits.amax(1)``.
    ``plane``/``row0``: accumulate into an existing plane, ``logits`` holding source rows
    ``row0 ..`` only (row bands or sample chunks: call once per chunk, then
    :func:`per_destination_exp` with the finished plane). No gradient flows through it.
    """
    k = kernel_size
    b, s, kk, h, w = logits.shape
    if kk != k * k:
        raise ValueError(f"expected {k * k} kernel taps, got {kk}")
    r = k // 2
    with torch.no_grad():
        m = logits.amax(dim=1)  # (B, K*K, h, W)
        if plane is None:
            plane = m.new_full((b, h + 2 * r, w + 2 * r), float("-inf"))
        for i in range(k):
            for j in range(k):
                # Source row y lands on padded row y + i (= (y + i - r) + r).
                dst = plane[:, row0 + i : row0 + i + h, j : j + w]
                torch.maximum(dst, m[:, i * k + j], out=dst)
    return plane


def per_destination_exp(
    logits: Tensor,
    kernel_size: int,
    plane: Tensor | None = None,
    *,
    row0: int = 0,
    inplace: bool = False,
) -> Tensor:
    """Exponentiate splat-kernel logits ``(B, S, K*K, H, W)`` so that normalisation stays exact.

    A splat output pixel ``u`` is normalised by the sum of all weights that land on ``u``, coming
    from different samples at different pixels. Subtracting a per-sample max (as a softmax would)
    rescales samples against each other and changes the result; a single global max is exact but
    lets a dim region underflow next to a bright one. Here every tap is shifted by a constant that
    depends only on its destination pixel ``u``: ``c(u)`` = the max of the logits that actually
    land on ``u`` (:func:`destination_max`). Tap ``t = (i, j)`` of a sample at ``x`` lands on
    ``u = x + (i - r, j - r)`` (flat index ``i*K + j``, ``r = K // 2``), the splat convention of
    :mod:`mcdenoise.ops.splat`. The shift is constant per destination, so it cancels exactly in
    the per-pixel normalisation, and the largest weight landing on every pixel is exactly 1: the
    weight sum is >= 1 and no ``eps`` can swamp it, whatever the logit gaps (issue 8, bug 1; a
    bound over all nearby samples instead let peaked kernels underflow to black pixels).

    ``plane`` ``(B, H_img + 2r, W + 2r)``, if given, is a finished :func:`destination_max` over
    *all* samples and rows: pass it when ``logits`` holds only a chunk of samples, or the source
    rows ``row0 .. row0 + H - 1``, so every chunk gets the same shift. ``inplace`` overwrites
    ``logits`` (fine under autograd for a raw convolution output) so the weights cost no memory
    beyond the logits.
    """
    b, s, kk, h, w = logits.shape
    k = kernel_size
    if kk != k * k:
        raise ValueError(f"expected {k * k} kernel taps, got {kk}")
    r = k // 2
    if plane is None:
        plane = destination_max(logits, k)
        row0 = 0
    with torch.no_grad():
        # Tap (i, j) at source y reads padded row y + i, column x + j: unfold gathers exactly that.
        band = plane[:, None, row0 : row0 + h + 2 * r].to(logits.dtype)
        shift = F.unfold(band, k).reshape(b, 1, kk, h, w)
    out = logits.sub_(shift) if inplace else logits - shift
    return out.exp_()
