"""The fast path of the WSKP importance filter (:mod:`mcdenoise.ops.importance` holds the contract,
the references and the numerics in its docstring): one shift per image and map with direct
power-of-two box sums (``_filter_one_shift``), the cache-banded CPU inference form of all sizes
and the fusion (``_filter_banded``), and the exact per-window-shifted fallback (``_filter_exact``)
for pixels whose window lies too far below the image maximum. Split from ``importance.py`` by
size; nothing here checks its arguments (the public functions do).
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["box_sum"]


def _tap_slices(x: Tensor, size: int, axis: int, pad_value: float) -> list[Tensor]:
    """Pad ``x`` by size // 2 on both ends of ``axis`` and return the k slices, one per window tap."""
    r = size // 2
    n = x.shape[axis]
    pad = [0, 0, 0, 0]
    pad[0 if axis == -1 else 2] = r
    pad[1 if axis == -1 else 3] = r
    xp = F.pad(x, pad, value=pad_value)
    return [xp.narrow(axis, t, n) for t in range(size)]


def _level_sums(x: Tensor, levels: int, dim: int, scratch: Sequence[Tensor] | None = None) -> list[Tensor]:
    """Power-of-two window sums along ``dim``: ``S[j][i] = sum_{t < 2**j} x[i + t]`` for j < levels.

    ``S[0]`` is ``x``; ``S[j]`` is the direct sum of two slices of ``S[j - 1]`` (one addition per
    element, no differences).  With ``scratch`` (flat tensors, one per level above 0) the sums are
    written into their leading elements (no autograd); without, they are new tensors.
    """
    sums = [x]
    for j in range(1, levels):
        prev, half = sums[-1], 1 << (j - 1)
        n = prev.shape[dim] - half
        a, b = prev.narrow(dim, 0, n), prev.narrow(dim, half, n)
        sums.append(a + b if scratch is None else torch.add(a, b, out=_view(scratch[j - 1], a.shape)))
    return sums


def _window_sums(sums: list[Tensor], size: int, length: int, dim: int, out: Tensor | None = None) -> Tensor:
    """``sum_{t < size} x[i + t]`` for i < length from the level sums of x (:func:`_level_sums`):
    one slice per set bit of ``size``, largest first, added directly (<= 4 terms for size <= 15)."""
    terms, off = [], 0
    for j in reversed(range(size.bit_length())):
        if size >> j & 1:
            terms.append(sums[j].narrow(dim, off, length))
            off += 1 << j
    if out is None:
        total = terms[0].clone() if len(terms) == 1 else terms[0] + terms[1]
        for t in terms[2:]:
            total = total + t
        return total
    if len(terms) == 1:
        return out.copy_(terms[0])
    torch.add(terms[0], terms[1], out=out)
    for t in terms[2:]:
        out.add_(t)
    return out


def _view(flat: Tensor, shape: Sequence[int]) -> Tensor:
    """The leading elements of a flat scratch tensor as a contiguous tensor of ``shape``."""
    n = 1
    for d in shape:
        n *= d
    return flat[:n].view(tuple(shape))


def box_sum(x: Tensor, size: int) -> Tensor:
    """Sum over the size x size window around each pixel, clipped at the border: (..., H, W) -> same.

    Separable direct sums over a zero-padded copy (no running-sum differences, so no
    cancellation): per axis, the power-of-two sums of :func:`_level_sums` and one slice of them per
    set bit of ``size``; cost O(log(size) H W).
    """
    if not isinstance(size, int) or size < 1 or size % 2 == 0:
        raise ValueError(f"box_sum: size must be a positive odd int, got {size!r}")
    lead = x.shape[:-2]
    y = x.reshape(-1, *x.shape[-2:])
    r = size // 2
    for dim, pad in ((-1, (r, r, 0, 0)), (-2, (0, 0, r, r))):
        n = y.shape[dim]
        y = _window_sums(_level_sums(F.pad(y, pad), size.bit_length(), dim), size, n, dim)
    return y.reshape(*lead, *x.shape[-2:])


def _shifted_window_sum(values: Tensor, log_w: Tensor, size: int, axis: int) -> tuple[Tensor, Tensor]:
    """One separable pass of the exact (per-window-shifted) filter along ``axis`` (-1 rows, -2 columns).

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


def _fallback_below(dtype: torch.dtype) -> float:
    """Denominators (relative to the image maximum) below which the exact path is used: tiny^(2/3),
    e^-58 in float32, e^-472 in float64 (see the module docstring)."""
    return torch.finfo(dtype).tiny ** (2 / 3)


def _filter_exact(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """The per-window-shifted filter, exact for any range of I (the fallback of the fast path).

    image (B, C, H, W) and importance (B, 1, H, W) in the accumulation dtype -> (B, C, H, W).
    """
    c = image.shape[1]
    # Numerator and denominator in one pass: the image with a ones channel.
    vals = torch.cat([image, torch.ones_like(importance)], dim=1)
    rows, m1 = _shifted_window_sum(vals, importance, size, -1)  # row sums relative to m1
    sums, _ = _shifted_window_sum(rows, m1, size, -2)  # relative to the window max; denominator >= 1
    return sums[:, :c] / sums[:, c:]


def _bounds(bad: Tensor) -> tuple[int, int, int, int]:
    """Rows [y0, y1) and columns [x0, x1) bounding the True pixels of ``bad`` (..., H, W) (some True)."""
    rows = bad.any(-1).reshape(-1, bad.shape[-2]).any(0).nonzero()
    cols = bad.any(-2).reshape(-1, bad.shape[-1]).any(0).nonzero()
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _exact_region(image: Tensor, importance: Tensor, size: int, region: tuple[int, int, int, int]) -> Tensor:
    """:func:`_filter_exact` at rows [y0, y1), columns [x0, x1) only, in the accumulation dtype.

    The crop keeps size // 2 more pixels on each side (where the image has them), so every window
    of the region is whole or clipped by the image border as in the full filter.
    """
    y0, y1, x0, x1 = region
    r, (h, w), acc = size // 2, image.shape[-2:], _acc_dtype(image)
    ya, yb, xa, xb = max(0, y0 - r), min(h, y1 + r), max(0, x0 - r), min(w, x1 + r)
    out = _filter_exact(image[..., ya:yb, xa:xb].to(acc), importance[..., ya:yb, xa:xb].to(acc), size)
    return out[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa]


def _filter_one_shift(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """Fast path with autograd (and on GPUs): box sums of ``exp(I - M)`` with one shift M per image,
    the exact path where the denominator is below :func:`_fallback_below`.  Accumulation dtype in
    and out; size > 1."""
    c = image.shape[1]
    # One shift per image: it cancels in the ratio, so detaching it is exact.
    e = torch.exp(importance - importance.detach().amax(dim=(-2, -1), keepdim=True))
    sums = box_sum(torch.cat([e * image, e], dim=1), size)
    num, den = sums[:, :c], sums[:, c:]
    bad = den < _fallback_below(den.dtype)
    if not bool(bad.any()):
        return num / den
    y0, y1, x0, x1 = region = _bounds(bad)
    h, w = image.shape[-2:]
    exact = F.pad(_exact_region(image, importance, size, region), (x0, w - x1, y0, h - y1))
    # Bad denominators are replaced before dividing, so no inf / NaN reaches the backward pass.
    return torch.where(bad, exact, num / torch.where(bad, torch.ones_like(den), den))


def _band_rows(h: int, w: int) -> int:
    # About 128k pixels per band (68 rows of 1920): the band's buffers (a few MB) stay in cache.
    # Measured on the 2-core CPU: 64k and 256k were 10-40% slower at 960 and 1920 wide.
    return max(8, min(h, (1 << 17) // max(w, 1)))


def _filter_banded(image: Tensor, importance: Tensor, fusion_logits: Tensor | None, sizes: Sequence[int]) -> Tensor:
    """No-autograd CPU fast path, the same arithmetic as :func:`_filter_one_shift` (one shift per
    image and map, power-of-two direct box sums, exact fallback below :func:`_fallback_below`),
    done band of rows by band of rows into preallocated buffers so the intermediates stay in cache.

    image (B, C, H, W), importance (B, N, H, W), fusion_logits (B, N, H, W) or None (then N = 1 and
    the single filtered image is returned).
    """
    acc = _acc_dtype(image)
    b, c, h, w = image.shape
    rmax = max(sizes) // 2
    levels = max(sizes).bit_length()
    dev = image.device
    out = torch.empty((b, c, h, w), dtype=acc, device=dev)
    shift = importance.amax(dim=(-2, -1), keepdim=True).to(acc)
    rows = _band_rows(h, w)
    nv = b * (c + 1) * (min(rows, h) + 2 * rmax) * w
    vbuf = torch.empty(nv, dtype=acc, device=dev)
    col_scratch = [torch.empty(nv, dtype=acc, device=dev) for _ in range(levels - 1)]
    # Column sums land between zero margins of rmax columns: the row pass reads its padding there.
    rowpad = torch.zeros((b, c + 1, min(rows, h), w + 2 * rmax), dtype=acc, device=dev)
    row_scratch = [torch.empty(rowpad.numel(), dtype=acc, device=dev) for _ in range(levels - 1)]
    boxbuf = torch.empty((b, c + 1, min(rows, h), w), dtype=acc, device=dev)
    wbuf = torch.empty((b, 1, min(rows, h), w), dtype=acc, device=dev)
    below = _fallback_below(acc)
    flagged: dict[int, list[tuple[int, int, Tensor, Tensor | None]]] = {}
    for y0 in range(0, h, rows):
        hb = min(rows, h - y0)
        o = out[:, :, y0 : y0 + hb]
        fusion = None if fusion_logits is None else torch.softmax(fusion_logits[:, :, y0 : y0 + hb].to(acc), dim=1)
        first = True
        for i, size in enumerate(sizes):
            fw = None if fusion is None else fusion[:, i : i + 1]
            if size == 1:  # the identity
                term = image[:, :, y0 : y0 + hb]
                if fw is None:
                    o.copy_(term)
                elif first:
                    torch.mul(term, fw, out=o)
                else:
                    o.addcmul_(term, fw)
                first = False
                continue
            r = size // 2
            # exp(I - M) and exp(I - M) c on rows [y0 - r, y0 + hb + r), zero outside the image.
            ya, yb = max(0, y0 - r), min(h, y0 + hb + r)
            top, n = ya - (y0 - r), hb + 2 * r
            v = _view(vbuf, (b, c + 1, n, w))
            if top:
                v[:, :, :top].zero_()
            if top + yb - ya < n:
                v[:, :, top + yb - ya :].zero_()
            vin = v[:, :, top : top + yb - ya]
            e = vin[:, c:]
            torch.sub(importance[:, i : i + 1, ya:yb], shift[:, i : i + 1], out=e).exp_()
            torch.mul(image[:, :, ya:yb], e, out=vin[:, :c])
            # Column pass into the middle of rowpad, then the row pass over its zero margins.
            rp = rowpad[:, :, :hb, rmax - r : rmax + w + r]
            _window_sums(_level_sums(v, size.bit_length(), -2, col_scratch), size, hb, -2, out=rp[..., r : r + w])
            box = boxbuf[:, :, :hb]
            _window_sums(_level_sums(rp, size.bit_length(), -1, row_scratch), size, w, -1, out=box)
            num, den = box[:, :c], box[:, c:]
            bad = None
            if float(den.amin()) < below:  # rare: some windows hold only negligible exp(I - M)
                bad = den < below
                den = torch.where(bad, torch.ones_like(den), den)
                flagged.setdefault(i, []).append((y0, hb, bad, None if fw is None else fw.clone()))
            if fw is None:
                torch.div(num, den, out=o)
            else:
                wt = torch.div(fw, den, out=wbuf[:, :, :hb])
                if bad is not None:
                    wt.masked_fill_(bad, 0)  # these pixels get the exact value after the loop
                if first:
                    torch.mul(num, wt, out=o)
                else:
                    o.addcmul_(num, wt)
            first = False
    # The exact path, once per flagged map, on the rectangle around its flagged pixels.
    for i, records in flagged.items():
        spans = [(y0 + r0, y0 + r1, x0, x1) for y0, _, bad, _ in records for r0, r1, x0, x1 in [_bounds(bad)]]
        region = (spans[0][0], spans[-1][1], min(t[2] for t in spans), max(t[3] for t in spans))
        ylo, _, x0, x1 = region
        exact = _exact_region(image, importance[:, i : i + 1], sizes[i], region)
        for (y0, _, bad, fw), (ra, rb, _, _) in zip(records, spans):
            ex = exact[:, :, ra - ylo : rb - ylo]
            o, bad = out[:, :, ra:rb, x0:x1], bad[..., ra - y0 : rb - y0, x0:x1]
            if fw is None:
                o.copy_(torch.where(bad, ex, o))
            else:
                o.add_(torch.where(bad, ex * fw[..., ra - y0 : rb - y0, x0:x1], torch.zeros_like(ex)))
    return out.to(image.dtype)


def _needs_grad(*tensors: Tensor) -> bool:
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
