"""Layer filtering and compositing (Munkberg and Hasselgren 2020, Eq. 3-6), exact under any
per-destination max shift.

Each layer ``j`` has per-pixel sums over its samples (Eq. 2): radiance ``l_rad`` (B, L, 3, h, w),
weight ``l_w`` and occupancy ``l_n`` (B, L, 1, h, w). Eq. 3 filters all three with the layer's
own kernel (exponentiated logits); Eq. 4-5 composite front to back with ``L^ = L-/n-`` and
``alpha = w-/n-``; Eq. 6 takes ``sum_j L-_j / sum_j w-_j``.

Exactness. Kernels are exponentiated after subtracting a shift that is constant per destination
pixel (:func:`mcdenoise.ops.kernels.per_destination_exp` for splats, a per-pixel max for
gathers), so every filtered sum at a pixel carries a factor ``exp(-shift)`` of any size, and only
ratios of sums filtered with one kernel are free of it. Hence: no eps is ever added to a
denominator (issue 8 bug 2: an eps of 1e-6 against sums scaled by exp(-30) blacked out every pixel
near a peaked kernel); :func:`safe_ratio` returns 0 only where the denominator is exactly 0 (then
nothing landed and the numerator is 0 too). And the denominator each ratio divides by is folded
into the logits: ``(den * x, den)`` filtered with ``exp(logit)`` equals ``(x, 1)`` filtered with
``exp(logit + log den)``, so after the shift the largest *weighted* tap reaching a pixel has
weight 1, even where the tap with the largest logit comes from a pixel with ``den = 0`` (a softmax
over layers that underflowed); such taps get logit ``-inf``. Eq. 4-5 divide within a layer, so
each layer gets its own shift; Eq. 6 sums over layers first, so one shift is shared.

Reference: ``tests/test_model_layer.py::_composite_reference`` (the equations with the unfold/fold
splat reference, no shift, no eps); the functions here agree with it to 1e-10 in float64.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from mcdenoise.ops.gather import gather
from mcdenoise.ops.kernels import destination_max, per_destination_exp
from mcdenoise.ops.splat import splat

__all__ = ["safe_ratio", "composite_layers", "splat_layer_sums", "gather_layer_sums"]

Sums = tuple[Tensor, Tensor, Tensor]


def safe_ratio(num: Tensor, den: Tensor) -> Tensor:
    """``num / den`` where ``den > 0``, else 0; num (B, C, H, W), den (B, 1, H, W).

    Scale-free, unlike ``num / (den + eps)``. The denominator is replaced before dividing (not
    only the quotient) so that pixels with ``den == 0`` give a zero gradient instead of NaN.
    """
    pos = den > 0
    return torch.where(pos, num / torch.where(pos, den, torch.ones_like(den)), torch.zeros_like(num))


def composite_layers(rad: Tensor, wbar: Tensor, nbar: Tensor, weighted: bool) -> Tensor:
    """Eq. 4-5 (front to back) or Eq. 6 from filtered sums: rad (B, L, 3, h, w), wbar and nbar
    (B, L, 1, h, w), each layer's sums sharing one positive factor per pixel (one factor for all
    layers with ``weighted``) -> (B, 3, h, w)."""
    if weighted:
        return safe_ratio(rad.sum(dim=1), wbar.sum(dim=1))
    out = torch.zeros_like(rad[:, 0])
    transmit = torch.ones_like(wbar[:, 0])
    for j in range(rad.shape[1]):
        out = out + transmit * safe_ratio(rad[:, j], nbar[:, j])
        # wbar_j <= nbar_j (w_j <= n_j before filtering), so the factor stays in [0, 1].
        transmit = transmit * (1 - safe_ratio(wbar[:, j], nbar[:, j]))
    return out


def _folded_values(l_rad: Tensor, l_w: Tensor, l_n: Tensor, weighted: bool) -> tuple[Tensor, Tensor]:
    """``(values (B, L, C, h, w), log den (B, L, 1, h, w))``: the values divided by the
    normalising sum (``l_w`` for Eq. 6, ``l_n`` for Eq. 4-5) plus an indicator channel that
    becomes the filtered denominator; ``-inf`` log where the sum is 0."""
    den = l_w if weighted else l_n
    pos = den > 0
    # The fold divides by a constant (detached) copy of the sum and the kernel weight multiplies it
    # back, so every filtered sum is linear in (l_rad, l_w, l_n) with the kernel as coefficient and
    # autograd gets that gradient directly. Dividing by the live sum gave the same values but made
    # autograd cancel two ~1/den terms; below den ~ 1e-19 (float32) each overflowed and inf - inf
    # gave NaN gradients (campaign 13: layer_optimized on a GPU, from step 10 on). The indicator
    # channel is den / const (1 where den > 0) so that the filtered denominator keeps its gradient.
    safe = torch.where(pos, den, torch.ones_like(den)).detach()
    parts = [l_rad / safe] if weighted else [l_rad / safe, l_w / safe]
    vals = torch.cat(parts + [den / safe], dim=2)
    return vals, torch.log(safe).masked_fill(~pos, float("-inf"))


def _split(num: Tensor, weighted: bool) -> Sums:
    """(B, L, C, h, w) filtered folded values -> (rad, wbar, nbar) for :func:`composite_layers`."""
    if weighted:  # the indicator channel is the filtered weight
        return num[:, :, :3], num[:, :, 3:4], num[:, :, 3:4]
    return num[:, :, :3], num[:, :, 3:4], num[:, :, -1:]


def splat_layer_sums(
    logits: Callable[[int, int], Tensor],
    l_rad: Tensor,
    l_w: Tensor,
    l_n: Tensor,
    kernel_size: int,
    *,
    weighted: bool,
    band_rows: int,
) -> Sums:
    """Eq. 3 with splats: each layer's sums spread with the layer's K x K kernels.

    Args:
        logits: ``(y0, y1) -> (B, L, K*K, y1 - y0, w)``, the kernel logits of source rows
            ``y0:y1`` (a fresh tensor or not: it is not modified).
        l_rad, l_w, l_n: layer sums (B, L, 3 | 1 | 1, h, w).
        weighted: Eq. 6 (one shift for all layers, and the splat sums over layers) or Eq. 4-5.
        band_rows: source rows per band. With ``band_rows < h`` no kernel-sized tensor of the whole
            image exists: a first pass (no autograd) records the per-destination maxima, a second
            regenerates each band's logits and splats them with K - 1 rows of zero-weight halo into
            one accumulator. With ``band_rows >= h`` the logits are generated once.

    Returns:
        (rad (B, L', 3, h, w), wbar, nbar (B, L', 1, h, w)), L' = 1 with ``weighted`` (already
        summed over layers), else L; input of :func:`composite_layers`.
    """
    b, nl, _, h, w = l_rad.shape
    k, kk, r = kernel_size, kernel_size**2, kernel_size // 2
    vals, log_den = _folded_values(l_rad, l_w, l_n, weighted)
    c = vals.shape[2]
    # Splat "samples" are the layers for Eq. 6 (their splats add up), single layers for Eq. 4-5.
    bs, ss = (b, nl) if weighted else (b * nl, 1)

    def folded(y0: int, y1: int) -> Tensor:
        # A fresh tensor (the add), so the exponentiation below may work in place.
        return (logits(y0, y1) + log_den[..., y0:y1, :]).reshape(bs, ss, kk, y1 - y0, w)

    plane = torch.full((bs, h + 2 * r, w + 2 * r), float("-inf"), dtype=l_rad.dtype, device=l_rad.device)
    whole = band_rows >= h
    if whole:
        lw = folded(0, h)
        destination_max(lw.detach(), k, plane=plane)
    else:
        # The shift of a destination needs every band's logits landing on it: maxima first.
        with torch.no_grad():
            for y0 in range(0, h, band_rows):
                destination_max(folded(y0, min(h, y0 + band_rows)), k, plane=plane, row0=y0)
    # A destination no finite tap lands on: any finite shift (only -inf taps go there).
    plane.masked_fill_(torch.isinf(plane), 0.0)
    v_all = vals.reshape(bs, ss, c, h, w)
    if whole:
        num, _ = splat(v_all, per_destination_exp(lw, k, plane, inplace=True))
    else:
        num = vals.new_zeros(bs, c, h, w)
        for y0 in range(0, h, band_rows):
            y1 = min(h, y0 + band_rows)
            wts = per_destination_exp(folded(y0, y1), k, plane, row0=y0, inplace=True)
            lo, hi = max(0, y0 - r), min(h, y1 + r)
            pad = (0, 0, y0 - lo, hi - y1)  # zero rows catch what the band splats beyond itself
            part, _ = splat(F.pad(v_all[..., y0:y1, :], pad), F.pad(wts, pad))
            num[..., lo:hi, :] += part
    return _split(num.reshape(b, -1, c, h, w), weighted)


def gather_layer_sums(
    logits: Tensor, l_rad: Tensor, l_w: Tensor, l_n: Tensor, kernel_size: int, *, weighted: bool
) -> Sums:
    """Eq. 3 with gathers (each pixel reads its K x K neighbours with its own kernel):
    logits (B, L, K*K, h, w) -> (rad (B, L, 3, h, w), wbar, nbar (B, L, 1, h, w)).

    The log of the normalising sum folded into each tap is that of the *neighbour* the tap
    reads; taps reading outside the image or a neighbour with sum 0 get -inf. The shift is the
    per-pixel max over taps (and over layers with ``weighted``).
    """
    b, nl, kk, h, w = logits.shape
    k = kernel_size
    vals, log_den = _folded_values(l_rad, l_w, l_n, weighted)
    c = vals.shape[2]
    padded = F.pad(log_den.reshape(b * nl, 1, h, w), (k // 2,) * 4, value=float("-inf"))
    lw = logits + F.unfold(padded, k).reshape(b, nl, kk, h, w)
    with torch.no_grad():
        m = lw.amax(dim=(1, 2) if weighted else 2, keepdim=True)
        m = m.masked_fill(torch.isinf(m), 0.0)  # nothing to read: any finite shift
    weights = torch.exp(lw - m)
    num = gather(vals.reshape(b * nl, c, h, w), weights.reshape(b * nl, kk, h, w))
    return _split(num.reshape(b, nl, c, h, w), weighted)
