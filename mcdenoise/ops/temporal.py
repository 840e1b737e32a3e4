"""Temporal accumulation for frame sequences (WSKP Sec. 4.1, after SVGF / BMFR).

The previous frame's result is reprojected to the current frame by per-pixel motion vectors with
bilinear sampling; each of the four bilinear taps is kept only where its world position and shading
normal agree with the current pixel's, and the kept taps are renormalised. Pixels with a usable
history are blended as ``alpha * current + (1 - alpha) * history``; the others (disocclusions,
pixels whose source lies outside the previous frame) keep the current value.

Conventions (see :mod:`mcdenoise.data.channels`): ``motion`` is the screen-space motion in pixels
from the previous frame to this one, so the current pixel ``(x, y)`` was at
``(x - motion_x, y - motion_y)`` in the previous frame; pixel centres sit on integer coordinates.
A miss has a zero normal; two misses are considered consistent (the sky is blended too).

Memory: the fast path holds four gathered copies of the previous frame (4 x B x C x H x W) plus
the tap weights; the reference path loops over pixels in Python and is for tests only.
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = [
    "reproject",
    "temporal_accumulate",
    "temporal_accumulate_reference",
    "TemporalAccumulation",
]

#: A pixel keeps its history only when the kept bilinear taps carry at least this much weight; a
#: smaller total would renormalise one far-off tap into a sharp, wrong value.
MIN_TAP_WEIGHT = 0.05
#: Normals shorter than this are misses.
MISS_NORMAL = 1e-3


def _check(name: str, t: torch.Tensor, like: torch.Tensor, channels: int | None) -> None:
    if t.dim() != 4 or t.shape[0] != like.shape[0] or t.shape[-2:] != like.shape[-2:]:
        raise ValueError(
            f"temporal: {name} must be (B, C, H, W) = ({like.shape[0]}, C, {like.shape[-2]}, "
            f"{like.shape[-1]}), got {tuple(t.shape)}"
        )
    if channels is not None and t.shape[1] != channels:
        raise ValueError(f"temporal: {name} must have {channels} channels, got {t.shape[1]}")


def _check_all(
    current: torch.Tensor,
    previous: torch.Tensor,
    motion: torch.Tensor,
    position: torch.Tensor,
    prev_position: torch.Tensor,
    normal: torch.Tensor,
    prev_normal: torch.Tensor,
    alpha: float,
) -> None:
    _check("previous", previous, current, current.shape[1])
    _check("motion", motion, current, 2)
    _check("position", position, current, 3)
    _check("prev_position", prev_position, current, 3)
    _check("normal", normal, current, 3)
    _check("prev_normal", prev_normal, current, 3)
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"temporal: alpha must be in [0, 1], got {alpha}")


def _consistent(
    pos: torch.Tensor,
    n: torch.Tensor,
    prev_pos: torch.Tensor,
    prev_n: torch.Tensor,
    position_tolerance: float,
    normal_cos: float,
) -> torch.Tensor:
    """Geometry test on ``(..., 3, ...)`` tensors with the vector on dim -3 -> bool, that dim kept."""
    miss = n.norm(dim=-3, keepdim=True) < MISS_NORMAL
    prev_miss = prev_n.norm(dim=-3, keepdim=True) < MISS_NORMAL
    close = (pos - prev_pos).norm(dim=-3, keepdim=True) <= position_tolerance
    aligned = (n * prev_n).sum(dim=-3, keepdim=True) >= normal_cos
    return (miss & prev_miss) | (~miss & ~prev_miss & close & aligned)


def reproject(
    previous: torch.Tensor,
    motion: torch.Tensor,
    position: torch.Tensor,
    prev_position: torch.Tensor,
    normal: torch.Tensor,
    prev_normal: torch.Tensor,
    *,
    position_tolerance: float = 0.05,
    normal_cos: float = 0.9,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear reprojection of ``previous`` with per-tap geometry rejection (fast path).

    Args:
        previous: (B, C, H, W) previous frame's result.
        motion: (B, 2, H, W) motion in pixels, previous -> current (x then y).
        position, prev_position: (B, 3, H, W) world positions of this and the previous frame.
        normal, prev_normal: (B, 3, H, W) unit shading normals (0 on a miss).
        position_tolerance: largest world-space distance between a tap and the pixel, scene units.
        normal_cos: smallest cosine between the two normals.

    Returns:
        ``(history (B, C, H, W), valid (B, 1, H, W) bool)``; history is 0 where not valid.
    """
    b, c, h, w = previous.shape
    dev, dt = previous.device, previous.dtype
    ys = torch.arange(h, device=dev, dtype=dt).view(1, h, 1)
    xs = torch.arange(w, device=dev, dtype=dt).view(1, 1, w)
    sx = xs - motion[:, 0].to(dt)
    sy = ys - motion[:, 1].to(dt)
    x0 = torch.floor(sx)
    y0 = torch.floor(sy)
    fx = sx - x0
    fy = sy - y0
    x0 = x0.long()
    y0 = y0.long()

    def flat(t: torch.Tensor) -> torch.Tensor:
        return t.reshape(b, t.shape[1], h * w)

    prev_flat = flat(previous)
    ppos_flat = flat(prev_position.to(dt))
    pn_flat = flat(prev_normal.to(dt))
    num = torch.zeros_like(previous)
    wsum = torch.zeros((b, 1, h, w), device=dev, dtype=dt)
    for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1)):
        tx, ty = x0 + dx, y0 + dy
        inside = (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
        idx = (ty.clamp(0, h - 1) * w + tx.clamp(0, w - 1)).view(b, 1, h * w)
        tap_pos = torch.gather(ppos_flat, 2, idx.expand(b, 3, h * w)).view(b, 3, h, w)
        tap_n = torch.gather(pn_flat, 2, idx.expand(b, 3, h * w)).view(b, 3, h, w)
        ok = _consistent(position.to(dt), normal.to(dt), tap_pos, tap_n, position_tolerance, normal_cos)
        ok = ok & inside.unsqueeze(1)
        wt = ((fx if dx else 1 - fx) * (fy if dy else 1 - fy)).unsqueeze(1) * ok.to(dt)
        tap = torch.gather(prev_flat, 2, idx.expand(b, c, h * w)).view(b, c, h, w)
        num = num + wt * tap
        wsum = wsum + wt
    valid = wsum >= MIN_TAP_WEIGHT
    # where() on both sides keeps the gradient finite where wsum is 0.
    history = torch.where(valid, num / torch.where(valid, wsum, torch.ones_like(wsum)), torch.zeros_like(num))
    return history, valid


def temporal_accumulate(
    current: torch.Tensor,
    previous: torch.Tensor,
    motion: torch.Tensor,
    position: torch.Tensor,
    prev_position: torch.Tensor,
    normal: torch.Tensor,
    prev_normal: torch.Tensor,
    alpha: float = 0.2,
    *,
    position_tolerance: float = 0.05,
    normal_cos: float = 0.9,
    impl: str = "fast",
) -> torch.Tensor:
    """Exponential moving average of reprojected history: (B, C, H, W) -> (B, C, H, W).

    ``out = alpha * current + (1 - alpha) * reproject(previous)`` where the reprojection is valid,
    else ``current``. ``alpha = 1`` returns ``current``. Shapes as in :func:`reproject`;
    ``impl="reference"`` runs the per-pixel Python loop (tiny images only).
    """
    _check_all(current, previous, motion, position, prev_position, normal, prev_normal, alpha)
    if impl == "reference":
        return temporal_accumulate_reference(
            current, previous, motion, position, prev_position, normal, prev_normal, alpha,
            position_tolerance=position_tolerance, normal_cos=normal_cos,
        )
    if impl != "fast":
        raise ValueError(f"temporal: impl must be 'fast' or 'reference', got {impl!r}")
    history, valid = reproject(
        previous, motion, position, prev_position, normal, prev_normal,
        position_tolerance=position_tolerance, normal_cos=normal_cos,
    )
    return torch.where(valid, alpha * current + (1 - alpha) * history, current)


def temporal_accumulate_reference(
    current: torch.Tensor,
    previous: torch.Tensor,
    motion: torch.Tensor,
    position: torch.Tensor,
    prev_position: torch.Tensor,
    normal: torch.Tensor,
    prev_normal: torch.Tensor,
    alpha: float = 0.2,
    *,
    position_tolerance: float = 0.05,
    normal_cos: float = 0.9,
) -> torch.Tensor:
    """Plain per-pixel loop with the same semantics as :func:`temporal_accumulate` (tests only)."""
    _check_all(current, previous, motion, position, prev_position, normal, prev_normal, alpha)
    b, c, h, w = current.shape
    rows = []
    for bi in range(b):
        out_b = []
        for y in range(h):
            for x in range(w):
                sx = x - float(motion[bi, 0, y, x])
                sy = y - float(motion[bi, 1, y, x])
                x0, y0 = math.floor(sx), math.floor(sy)
                # Kept as tensors so gradients reach the motion vectors.
                fx = (x - motion[bi, 0, y, x].to(current.dtype)) - x0
                fy = (y - motion[bi, 1, y, x].to(current.dtype)) - y0
                num = current.new_zeros(c)
                wsum = current.new_zeros(())
                p = position[bi, :, y, x]
                n = normal[bi, :, y, x]
                for dy in (0, 1):
                    for dx in (0, 1):
                        tx, ty = x0 + dx, y0 + dy
                        if not (0 <= tx < w and 0 <= ty < h):
                            continue
                        pp = prev_position[bi, :, ty, tx]
                        pn = prev_normal[bi, :, ty, tx]
                        miss, pmiss = bool(n.norm() < MISS_NORMAL), bool(pn.norm() < MISS_NORMAL)
                        if miss or pmiss:
                            ok = miss and pmiss
                        else:
                            ok = bool((p - pp).norm() <= position_tolerance) and bool((n * pn).sum() >= normal_cos)
                        if not ok:
                            continue
                        wt = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
                        num = num + wt * previous[bi, :, ty, tx]
                        wsum = wsum + wt
                cur = current[bi, :, y, x]
                if float(wsum) >= MIN_TAP_WEIGHT:
                    out_b.append(alpha * cur + (1 - alpha) * num / wsum)
                else:
                    out_b.append(cur)
        rows.append(torch.stack(out_b, dim=-1).view(c, h, w))
    return torch.stack(rows, dim=0)


class TemporalAccumulation(nn.Module):
    """Thin module around :func:`temporal_accumulate` holding the blend factor and tolerances."""

    def __init__(self, alpha: float = 0.2, position_tolerance: float = 0.05, normal_cos: float = 0.9) -> None:
        super().__init__()
        self.alpha = alpha
        self.position_tolerance = position_tolerance
        self.normal_cos = normal_cos

    def forward(
        self,
        current: torch.Tensor,
        previous: torch.Tensor,
        motion: torch.Tensor,
        position: torch.Tensor,
        prev_position: torch.Tensor,
        normal: torch.Tensor,
        prev_normal: torch.Tensor,
    ) -> torch.Tensor:
        return temporal_accumulate(
            current, previous, motion, position, prev_position, normal, prev_normal, self.alpha,
            position_tolerance=self.position_tolerance, normal_cos=self.normal_cos,
        )
