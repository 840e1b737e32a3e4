"""Multi-scale composition: the layer paper's 3-level kernel hierarchy and WSKP's multi-resolution blend.

Pyramid helpers (shared by both):
* :func:`downsample2` -- 2 x 2 box average, (H, W) -> (ceil(H/2), ceil(W/2)); an odd last row or
  column is averaged with itself (i.e. only in-image pixels count).
* :func:`upsample2` -- nearest-neighbour 2x, cropped to the requested size.
With these, ``downsample2(upsample2(x, size)) == x`` exactly for any size.

Layer paper (Munkberg & Hasselgren 2020, Sec. 6, Eq. 10), as we read it: the radiance is filtered
with a 5 x 5 kernel at full, 1/2 and 1/4 resolution (the inputs of level i are the level i-1
inputs downscaled by 2); each level is processed to completion (normalised) giving G_i, and the
result is ``sum_i Upscale(G_i, 2^i) * lambda_i`` with lambda_i output by the kernel generator.  The
paper names neither the down- nor the up-scaling filter; we use the 2 x 2 box and nearest
neighbour (the operators WSKP Eq. 7 names), applied one octave at a time so odd sizes work.  The
layer paper applies its kernels as splats, so :func:`hierarchical_filter` offers ``mode="splat"``
(each pixel splats itself, normalised per output pixel) besides ``mode="gather"``.

WSKP (Fan et al. 2021, Eq. 7): ``o = i_f - alpha * U(D(i_f)) + alpha * U(i_c)``: the coarse
result replaces the low frequencies of the fine one where alpha is 1.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from mcdenoise.ops._common import check_tensor
from mcdenoise.ops.gather import gather
from mcdenoise.ops.splat import normalize_splat, splat

__all__ = [
    "downsample2",
    "upsample2",
    "build_pyramid",
    "combine_levels",
    "hierarchical_filter",
    "multires_blend",
    "HierarchicalFilter",
    "MultiresBlend",
]


def downsample2(x: Tensor) -> Tensor:
    """2 x 2 box average: (B, C, H, W) -> (B, C, ceil(H/2), ceil(W/2))."""
    check_tensor(x, "x", 4, "(B, C, H, W)", "downsample2")
    h, w = x.shape[-2:]
    # Replicating an odd last row/column makes its 2 x 2 average the mean of in-image pixels.
    if h % 2:
        x = torch.cat([x, x[..., -1:, :]], dim=-2)
    if w % 2:
        x = torch.cat([x, x[..., -1:]], dim=-1)
    b, c, h2, w2 = x.shape
    # reshape + mean rather than F.pad(replicate)/avg_pool2d: same numbers, but those enter an
    # OpenMP parallel region even for tiny tensors, measured at ~20 ms per call on our
    # oversubscribed 2-core machine.
    return x.reshape(b, c, h2 // 2, 2, w2 // 2, 2).mean(dim=(3, 5))


def upsample2(x: Tensor, size: Sequence[int]) -> Tensor:
    """Nearest-neighbour 2x: (B, C, h, w) -> (B, C, H, W) with H in {2h - 1, 2h}, W in {2w - 1, 2w}."""
    check_tensor(x, "x", 4, "(B, C, h, w)", "upsample2")
    hh, ww = int(size[0]), int(size[1])
    h, w = x.shape[-2:]
    if (hh + 1) // 2 != h or (ww + 1) // 2 != w:
        raise ValueError(
            f"upsample2: size {(hh, ww)} is not a 2x upsampling of {(h, w)} (need ceil(size / 2) == input size)"
        )
    up = x.repeat_interleave(2, dim=-2).repeat_interleave(2, dim=-1)
    return up[..., :hh, :ww]


def build_pyramid(x: Tensor, levels: int) -> list[Tensor]:
    """[x, D x, D D x, ...] with ``levels`` entries; x (B, C, H, W)."""
    if levels < 1:
        raise ValueError(f"build_pyramid: levels must be >= 1, got {levels}")
    out = [x]
    for _ in range(levels - 1):
        out.append(downsample2(out[-1]))
    return out


def _upsample_to(x: Tensor, sizes: Sequence[tuple[int, int]]) -> Tensor:
    # sizes: the pyramid sizes from this level's parent up to level 0, coarse to fine.
    for s in sizes:
        x = upsample2(x, s)
    return x


def _level_weights(level_weights: Tensor, levels: int, b: int, op: str) -> Tensor:
    """Broadcastable (B or 1, L, 1 or H, 1 or W) view of (L,), (B, L) or (B, L, H, W) weights."""
    doc = f"(L={levels},), (B, L) or (B, L, H, W)"
    if not isinstance(level_weights, Tensor):
        raise TypeError(f"{op}: level_weights must be a tensor of shape {doc}")
    if level_weights.dim() == 1 and level_weights.shape[0] == levels:
        return level_weights.reshape(1, levels, 1, 1)
    if level_weights.dim() == 2 and level_weights.shape[1] == levels:
        return level_weights.reshape(level_weights.shape[0], levels, 1, 1)
    if level_weights.dim() == 4 and level_weights.shape[1] == levels:
        return level_weights
    raise ValueError(f"{op}: level_weights must have shape {doc}, got {tuple(level_weights.shape)}")


def combine_levels(levels: Sequence[Tensor], level_weights: Tensor) -> Tensor:
    """Layer paper Eq. 10: ``sum_i Upscale(G_i, 2^i) * lambda_i``.

    Args:
        levels: L tensors, ``levels[i]`` of shape (B, C, H_i, W_i) with H_i = ceil(H_{i-1} / 2).
        level_weights: (L,), (B, L) or (B, L, H, W) (per-pixel lambda at full resolution).

    Returns:
        (B, C, H, W) at the resolution of ``levels[0]``.
    """
    op = "combine_levels"
    if len(levels) < 1:
        raise ValueError(f"{op}: need at least one level")
    sizes = [tuple(int(v) for v in g.shape[-2:]) for g in levels]
    for i in range(1, len(levels)):
        ph, pw = sizes[i - 1]
        if sizes[i] != ((ph + 1) // 2, (pw + 1) // 2):
            raise ValueError(f"{op}: level {i} has size {sizes[i]}, expected ceil(level {i-1} size / 2) = "
                             f"{((ph + 1) // 2, (pw + 1) // 2)}")
    lw = _level_weights(level_weights, len(levels), levels[0].shape[0], op)
    out = None
    for i, g in enumerate(levels):
        up = _upsample_to(g, sizes[:i][::-1])
        term = lw[:, i : i + 1] * up
        out = term if out is None else out + term
    return out  # type: ignore[return-value]


def hierarchical_filter(
    image: Tensor,
    weights: Sequence[Tensor],
    level_weights: Tensor,
    *,
    mode: str = "gather",
    eps: float = 1e-10,
    impl: str = "auto",
) -> Tensor:
    """Filter a pyramid of ``image`` with one small kernel per pixel per level and combine (Eq. 10).

    Args:
        image: (B, C, H, W) at full resolution.
        weights: L tensors (3 in the paper), ``weights[i]`` (B, K*K, H_i, W_i) (K = 5 in the paper)
            with H_0 = H and H_i = ceil(H_{i-1} / 2).  Used as given in "gather" mode; in "splat"
            mode each pixel splats itself with its kernel and the level is normalised by the
            splatted weight sum.
        level_weights: (L,), (B, L) or (B, L, H, W) lambda_i.
        mode: "gather" or "splat".
        eps: added to the weight sum in splat mode.

    Returns:
        (B, C, H, W) ``sum_i lambda_i Upscale(filter_i(D^i image))``.
    """
    op = "hierarchical_filter"
    check_tensor(image, "image", 4, "(B, C, H, W)", op)
    if mode not in ("gather", "splat"):
        raise ValueError(f"{op}: mode must be 'gather' or 'splat', got {mode!r}")
    if len(weights) < 1:
        raise ValueError(f"{op}: weights must hold one (B, K*K, H_i, W_i) tensor per level")
    pyramid = build_pyramid(image, len(weights))
    filtered = []
    for i, (x, w) in enumerate(zip(pyramid, weights)):
        check_tensor(w, f"weights[{i}]", 4, "(B, K*K, H_i, W_i)", op)
        if w.shape[0] != x.shape[0] or w.shape[-2:] != x.shape[-2:]:
            raise ValueError(
                f"{op}: weights[{i}] must have shape (B, K*K, H_i, W_i) = ({x.shape[0]}, K*K, "
                f"{x.shape[2]}, {x.shape[3]}), got {tuple(w.shape)}"
            )
        if mode == "gather":
            filtered.append(gather(x, w, impl=impl))
        else:
            num, wsum = splat(x.unsqueeze(1), w.unsqueeze(1), impl=impl)
            filtered.append(normalize_splat(num, wsum, eps))
    return combine_levels(filtered, level_weights)


def multires_blend(fine: Tensor, coarse: Tensor, alpha: Tensor) -> Tensor:
    """WSKP Eq. 7: ``fine - alpha * U(D(fine)) + alpha * U(coarse)``.

    Args:
        fine: (B, C, H, W) result at the fine resolution.
        coarse: (B, C, ceil(H/2), ceil(W/2)) result at the next coarser resolution.
        alpha: (B, 1, H, W) per-pixel blend weight (usually in [0, 1]).

    Returns:
        (B, C, H, W).  With ``coarse == downsample2(fine)`` the output is ``fine`` for any alpha.
    """
    op = "multires_blend"
    check_tensor(fine, "fine", 4, "(B, C, H, W)", op)
    check_tensor(coarse, "coarse", 4, "(B, C, ceil(H/2), ceil(W/2))", op)
    check_tensor(alpha, "alpha", 4, "(B, 1, H, W)", op)
    b, c, h, w = fine.shape
    want = (b, c, (h + 1) // 2, (w + 1) // 2)
    if tuple(coarse.shape) != want:
        raise ValueError(f"{op}: coarse must have shape (B, C, ceil(H/2), ceil(W/2)) = {want}, got {tuple(coarse.shape)}")
    if alpha.shape[0] != b or alpha.shape[1] not in (1, c) or alpha.shape[-2:] != fine.shape[-2:]:
        raise ValueError(f"{op}: alpha must have shape (B, 1, H, W) = ({b}, 1, {h}, {w}), got {tuple(alpha.shape)}")
    # U is linear, so U(coarse) - U(D(fine)) = U(coarse - D(fine)): one upsampling instead of two.
    return fine + alpha * upsample2(coarse - downsample2(fine), (h, w))


class HierarchicalFilter(nn.Module):
    """Module form of :func:`hierarchical_filter`."""

    def __init__(self, mode: str = "gather", eps: float = 1e-10, impl: str = "auto") -> None:
        super().__init__()
        self.mode, self.eps, self.impl = mode, eps, impl

    def forward(self, image: Tensor, weights: Sequence[Tensor], level_weights: Tensor) -> Tensor:
        return hierarchical_filter(image, weights, level_weights, mode=self.mode, eps=self.eps, impl=self.impl)


class MultiresBlend(nn.Module):
    """Module form of :func:`multires_blend`."""

    def forward(self, fine: Tensor, coarse: Tensor, alpha: Tensor) -> Tensor:
        return multires_blend(fine, coarse, alpha)
