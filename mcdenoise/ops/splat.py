"""Per-sample kernel splatting (SBMC Eq. 1, PixelSplat, the layer paper's filtering).

Each sample ``s`` at pixel ``p`` spreads its value to the K x K pixels around ``p`` with its own
kernel: ``num[b, :, p + d] += w[b, s, ij, p] * values[b, s, :, p]`` and ``wsum[b, 0, p + d] +=
w[b, s, ij, p]``, ``d = (i - r, j - r)`` for tap ``i * K + j``.  Contributions landing outside the
image are dropped.  The denoised image is ``num / (wsum + eps)`` (:func:`normalize_splat`).

Memory (float32, B images, S samples, C channels, H x W, K x K kernels):
* the inputs themselves: ``4 B S K^2 H W`` bytes of weights dominate (3.6 GB per sample at 1080p,
  K = 21; 117 GB for 32 spp).  A caller that cannot hold all samples' kernels generates them per
  chunk of samples and feeds :class:`SplatAccumulator`, so only one chunk's kernels exist at once.
* reference: the fold input, ``4 B C K^2 H W`` bytes, plus ``4 B S C K^2 H W`` for the
  per-sample products (kept by autograd).
* fast: forward allocates only the padded accumulator ``4 B (C+1)(H+2r)(W+2r)`` bytes; backward
  keeps only the inputs and produces the gradients chunk by chunk of samples (its temporaries
  are one padded copy of the output gradient per chunk besides the gradients themselves).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mcdenoise.ops._common import check_same, check_tensor, kernel_size_from, resolve_impl
from mcdenoise.ops._shift import CorrelateFn, GatherFn, correlate_core, gather_core

__all__ = [
    "splat",
    "splat_reference",
    "splat_fast",
    "normalize_splat",
    "Splat",
    "SplatAccumulator",
    "default_chunk",
    "splat_into_",
]

_V = "(B, S, C, H, W)"
_W = "(B, S, K*K, H, W)"

# Default number of elements of one backward step's (B, chunk, C, H, W) block.
_CHUNK_BUDGET_ELEMS = 1 << 24


def _check(values: Tensor, weights: Tensor, op: str) -> int:
    check_tensor(values, "values", 5, _V, op)
    check_tensor(weights, "weights", 5, _W, op)
    check_same(values, weights, "values and weights", op)
    b, s, _, h, w = values.shape
    if weights.shape[:2] != values.shape[:2] or weights.shape[-2:] != values.shape[-2:]:
        raise ValueError(
            f"{op}: weights must have shape {_W} = ({b}, {s}, K*K, {h}, {w}) to match values "
            f"{tuple(values.shape)}, got {tuple(weights.shape)}"
        )
    return kernel_size_from(weights.shape[2], "weights", _W, op)


def default_chunk(values: Tensor) -> int:
    """Samples per backward step of the fast path (all of them up to a ~64 MB float32 block)."""
    b, s, c, h, w = values.shape
    return max(1, min(s, _CHUNK_BUDGET_ELEMS // max(1, b * c * h * w)))


def splat_into_(values: Tensor, weights: Tensor, acc: Tensor, row0: int = 0) -> Tensor:
    """Add the splat of a band of source rows into a padded accumulator, in place (inference only).

    values (B, S, C, h, W), weights (B, S, K*K, h, W) for source rows ``row0 .. row0 + h - 1``;
    acc (B, C + 1, H + 2r, W + 2r): numerator channels then the weight sum, padded by ``r = K // 2``
    on every side so that contributions of a band to the rows above and below it (and to outside
    the image, cropped by the caller as ``acc[..., r:r+H, r:r+W]``) land somewhere. Lets a model
    generate and splat kernels one row band at a time, so only one band's kernels exist at once.
    No autograd: raises if any input requires a gradient (use :func:`splat` for training).
    """
    k = _check(values, weights, "splat_into_")
    if torch.is_grad_enabled() and (values.requires_grad or weights.requires_grad):
        raise RuntimeError("splat_into_ is inference-only; use splat() where gradients are needed")
    b, _, c, h, w = values.shape
    r = k // 2
    if acc.dim() != 4 or acc.shape[0] != b or acc.shape[1] != c + 1 or acc.shape[-1] != w + 2 * r:
        raise ValueError(f"splat_into_: acc must be (B, C+1, H+2r, W+2r) with B={b}, C+1={c + 1}, W+2r={w + 2 * r}")
    if row0 < 0 or row0 + h + 2 * r > acc.shape[2]:
        raise ValueError(f"splat_into_: rows {row0}..{row0 + h} do not fit an accumulator of {acc.shape[2]} padded rows")
    _splat_add_(acc[:, :, row0 : row0 + h + 2 * r], values, weights, k)
    return acc


def splat_reference(values: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Fold-based splat, written for clarity.

    values (B,S,C,H,W), weights (B,S,K*K,H,W) -> (numerator (B,C,H,W), weight_sum (B,1,H,W)).
    """
    k = _check(values, weights, "splat_reference")
    b, s, c, h, w = values.shape
    # fold is the adjoint of unfold: block entry (c, i, j) at location p is added to p + (i-r, j-r).
    contrib = (values.unsqueeze(3) * weights.unsqueeze(2)).sum(dim=1)  # (B, C, K*K, H, W)
    num = F.fold(contrib.reshape(b, c * k * k, h * w), (h, w), kernel_size=k, padding=k // 2)
    wsum = F.fold(weights.sum(dim=1).reshape(b, k * k, h * w), (h, w), kernel_size=k, padding=k // 2)
    return num, wsum


def _splat_core(values: Tensor, weights: Tensor, k: int) -> Tensor:
    """(B,S,C,H,W), (B,S,K*K,H,W) -> (B, C+1, H, W): numerator channels then the weight sum.

    One in-place multiply-add per sample and offset; the only temporary is one sample's values
    with a ones channel (a chunked ``(v * w).sum(samples)`` was 7x slower on CPU).
    """
    b, _, c, h, w = values.shape
    r = k // 2
    outp = values.new_zeros((b, c + 1, h + 2 * r, w + 2 * r))
    _splat_add_(outp, values, weights, k)
    return outp[:, :, r : r + h, r : r + w].contiguous()


def _splat_add_(outp: Tensor, values: Tensor, weights: Tensor, k: int) -> None:
    """Add the splat of values (B,S,C,h,W), weights (B,S,K*K,h,W) into ``outp`` (B, C+1, h+2r, W+2r),
    padded by ``r = K // 2`` on every side, in place: numerator channels then the weight sum."""
    h, w = values.shape[-2:]
    for si in range(values.shape[1]):
        # The ones channel turns the weight sum into one more channel of the same multiply-add.
        v = torch.cat([values[:, si], torch.ones_like(values[:, si, :1])], dim=1)  # (B, C+1, h, W)
        ws = weights[:, si]
        for i in range(k):
            for j in range(k):
                t = i * k + j
                outp[:, :, i : i + h, j : j + w].addcmul_(v, ws[:, t : t + 1])


class _SplatFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values: Tensor, weights: Tensor, k: int, chunk: int) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(values, weights)
        ctx.k, ctx.chunk = k, chunk
        return _splat_core(values, weights, k)

    @staticmethod
    def backward(ctx, g: Tensor):  # type: ignore[override]
        # g: (B, C+1, H, W).  d out[c, p+d] / d v[s, c, p] = w[s, ij, p]  -> gather of g's colour part;
        # d out[:, p+d] / d w[s, ij, p] = (v[s, :, p], 1)                  -> correlate with all of g.
        values, weights = ctx.saved_tensors
        k, chunk = ctx.k, ctx.chunk
        c = values.shape[2]
        g_col = g[:, None, :c]
        g_all = g[:, None]
        need_v, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        s_total = values.shape[1]
        if torch.is_grad_enabled():
            # create_graph=True: build the gradients from differentiable pieces (double backward).
            gv_parts: list[Tensor] = []
            gw_parts: list[Tensor] = []
            for s0 in range(0, s_total, chunk):
                v = values[:, s0 : s0 + chunk]
                wc = weights[:, s0 : s0 + chunk]
                if need_v:
                    gv_parts.append(GatherFn.apply(g_col, wc, k))
                if need_w:
                    v_aug = torch.cat([v, torch.ones_like(v[:, :, :1])], dim=2)
                    gw_parts.append(CorrelateFn.apply(v_aug, g_all, k))
            gv = torch.cat(gv_parts, dim=1) if need_v else None
            gw = torch.cat(gw_parts, dim=1) if need_w else None
            return gv, gw, None, None
        # Plain backward: write each chunk straight into the gradient tensors (no concatenation).
        gv = torch.empty_like(values) if need_v else None
        gw = torch.empty_like(weights) if need_w else None
        # The weight-sum channel: d wsum[p+d] / d w[s, ij, p] = 1, the same for every sample.
        g_wsum = correlate_core(torch.ones_like(g[:, None, :1]), g[:, None, c:], k) if need_w else None
        for s0 in range(0, s_total, chunk):
            s1 = min(s0 + chunk, s_total)
            if gv is not None:
                gather_core(g_col, weights[:, s0:s1], k, out=gv[:, s0:s1])
            if gw is not None:
                gws = gw[:, s0:s1]
                correlate_core(values[:, s0:s1], g_col, k, out=gws)
                gws.add_(g_wsum)
        return gv, gw, None, None


def splat_fast(values: Tensor, weights: Tensor, *, chunk: int | None = None) -> tuple[Tensor, Tensor]:
    """Shift-and-accumulate splat chunked over samples; same contract as :func:`splat`."""
    k = _check(values, weights, "splat")
    if chunk is None:
        chunk = default_chunk(values)
    if chunk < 1:
        raise ValueError(f"splat: chunk must be >= 1, got {chunk}")
    out = _SplatFn.apply(values, weights, k, int(chunk))
    c = values.shape[2]
    return out[:, :c], out[:, c:]


def splat(
    values: Tensor, weights: Tensor, *, chunk: int | None = None, impl: str = "auto"
) -> tuple[Tensor, Tensor]:
    """Splat every sample with its own K x K kernel.

    Args:
        values: (B, S, C, H, W) per-sample values (radiance, or anything to be filtered).
        weights: (B, S, K*K, H, W) per-sample kernels, K odd, tap ``i * K + j`` sending to offset
            ``(i - K//2, j - K//2)``.  Used as given (e.g. from :func:`mcdenoise.ops.kernels.exp_kernel`).
        chunk: samples per step of the fast path's backward (default: all samples up to a
            ~64 MB gradient block); results do not depend on it.
        impl: "auto" | "reference" | "fast".

    Returns:
        ``(numerator (B, C, H, W), weight_sum (B, 1, H, W))``; out-of-image contributions dropped.
    """
    if resolve_impl(impl, "splat") == "reference":
        return splat_reference(values, weights)
    return splat_fast(values, weights, chunk=chunk)


def normalize_splat(num: Tensor, wsum: Tensor, eps: float = 1e-10) -> Tensor:
    """SBMC Eq. 1: ``num / (wsum + eps)``; num (B,C,H,W), wsum (B,1,H,W) -> (B,C,H,W)."""
    check_tensor(num, "num", 4, "(B, C, H, W)", "normalize_splat")
    check_tensor(wsum, "wsum", 4, "(B, 1, H, W)", "normalize_splat")
    if wsum.shape[1] != 1 or wsum.shape[0] != num.shape[0] or wsum.shape[-2:] != num.shape[-2:]:
        raise ValueError(
            f"normalize_splat: wsum must have shape (B, 1, H, W) = ({num.shape[0]}, 1, "
            f"{num.shape[2]}, {num.shape[3]}), got {tuple(wsum.shape)}"
        )
    return num / (wsum + eps)


class Splat(nn.Module):
    """Module form of splat + normalisation: ``forward(values, weights) -> (B, C, H, W)``."""

    def __init__(self, eps: float = 1e-10, chunk: int | None = None, impl: str = "auto") -> None:
        super().__init__()
        self.eps, self.chunk, self.impl = eps, chunk, impl

    def forward(self, values: Tensor, weights: Tensor) -> Tensor:
        num, wsum = splat(values, weights, chunk=self.chunk, impl=self.impl)
        return normalize_splat(num, wsum, self.eps)


class SplatAccumulator:
    """Sums splats of successive sample chunks so only one chunk's kernels need to exist at once.

    Usage::

        acc = SplatAccumulator()
        for s0 in range(0, S, 4):
            acc.add(values[:, s0:s0+4], predict_kernels(s0, s0 + 4))  # (B,s,C,H,W), (B,s,K*K,H,W)
        image = acc.normalized()

    Differentiable (the sum of differentiable splats); memory beyond the chunk is the two
    accumulators, ``4 B (C + 1) H W`` bytes.
    """

    def __init__(self, *, chunk: int | None = None, impl: str = "auto") -> None:
        self.chunk, self.impl = chunk, impl
        self.num: Tensor | None = None
        self.wsum: Tensor | None = None

    def add(self, values: Tensor, weights: Tensor) -> None:
        """Splat one chunk: values (B,s,C,H,W), weights (B,s,K*K,H,W)."""
        num, wsum = splat(values, weights, chunk=self.chunk, impl=self.impl)
        if self.num is None or self.wsum is None:
            self.num, self.wsum = num, wsum
        else:
            if num.shape != self.num.shape:
                raise ValueError(
                    f"SplatAccumulator.add: chunk splats to {tuple(num.shape)}, earlier chunks to "
                    f"{tuple(self.num.shape)}"
                )
            self.num, self.wsum = self.num + num, self.wsum + wsum

    def result(self) -> tuple[Tensor, Tensor]:
        """(numerator (B,C,H,W), weight_sum (B,1,H,W)) of everything added."""
        if self.num is None or self.wsum is None:
            raise ValueError("SplatAccumulator.result: nothing was added")
        return self.num, self.wsum

    def normalized(self, eps: float = 1e-10) -> Tensor:
        """``num / (wsum + eps)`` (B, C, H, W)."""
        num, wsum = self.result()
        return normalize_splat(num, wsum, eps)
