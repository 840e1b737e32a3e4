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


def importance_filter_fast(image: Tensor, importance: Tensor, size: int) -> Tensor:
    """Box sums of ``exp(I - M)`` (one shift per image) with the exact per-window-shifted path where
    they underflow; same contract as :func:`importance_filter` (see the module docstring)."""
    _check(image, importance, size, "importance_filter")
    if size == 1:
        return image.clone()
    if image.device.type == "cpu" and not _needs_grad(image, importance):
        return _filter_banded(image, importance, None, (size,))
    acc = _acc_dtype(image)
    return _filter_one_shift(image.to(acc), importance.to(acc), size).to(image.dtype)


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
        and not _needs_grad(image, importance, fusion_logits)
    ):
        # All N filters and the fusion in one pass over bands of rows (same arithmetic as below).
        return _filter_banded(image, importance, fusion_logits, sizes)
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
