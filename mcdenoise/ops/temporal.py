"""Temporal accumulation for frame sequences (WSKP Sec. 4.1, after SVGF / BMFR).

The previous frame's result is reprojected to the current frame by per-pixel motion vectors with
bilinear sampling; each of the four bilinear taps is kept only where its world position and shading
normal agree with the current pixel's, and the kept taps are renormalised. A per-pixel history
length ``n`` (frames accumulated) is reprojected with the same taps: pixels with a usable history
get ``n = n_prev + 1`` and are blended as ``a * current + (1 - a) * history`` with
``a = max(alpha, 1 / n)``, as SVGF and BMFR do, so the first ``1 / alpha`` frames give their
running mean and later ones an exponential moving average; the others (disocclusions, pixels whose
source lies outside the previous frame) restart at ``n = 1`` and keep the current value.  A fixed
``alpha`` from the first frame (issue 8 item 9) would make frame 2 ``0.2 x frame 2 + 0.8 x frame 1``:
mostly the one earlier frame, as noisy as it.  ``n`` is capped at ``1 / alpha``, beyond which it
changes nothing, so a bilinear tap mixing an old and a new history stays meaningful.

Conventions (see :mod:`mcdenoise.data.channels`): ``motion`` is the screen-space motion in pixels
from the previous frame to this one, so the current pixel ``(x, y)`` was at
``(x - motion_x, y - motion_y)`` in the previous frame; pixel centres sit on integer coordinates.
A miss has a zero normal; two misses are considered consistent (the sky is blended too).

Memory: the fast path gathers the previous frame and its history length tap by tap (a few
B x (C + 1) x H x W buffers) plus the tap weights; the reference path loops over pixels in Python and is for tests only.
"""

from __future__ import annotations

import math

import torch
from torch import nn

__all__ = [
    "reproject",
    "history_alpha",
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
    history_length: torch.Tensor,
    alpha: float,
) -> None:
    _check("previous", previous, current, current.shape[1])
    _check("history_length", history_length, current, 1)
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


def history_alpha(n: torch.Tensor, alpha: float) -> torch.Tensor:
    """Blend weight of the current frame for history lengths ``n`` (>= 1, any shape): ``max(alpha, 1/n)``."""
    return torch.clamp(1.0 / n, min=alpha)


def _cap(alpha: float) -> float:
    return 1.0 / alpha if alpha > 0 else math.inf


def temporal_accumulate(
    current: torch.Tensor,
    previous: torch.Tensor,
    motion: torch.Tensor,
    position: torch.Tensor,
    prev_position: torch.Tensor,
    normal: torch.Tensor,
    prev_normal: torch.Tensor,
    history_length: torch.Tensor,
    alpha: float = 0.2,
    *,
    position_tolerance: float = 0.05,
    normal_cos: float = 0.9,
    impl: str = "fast",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Running mean, then exponential moving average, of reprojected history (SVGF / BMFR rule).

    Args:
        current: (B, C, H, W) this frame's noisy input.
        previous: (B, C, H, W) the previous frame's accumulated result.
        motion, position, prev_position, normal, prev_normal: as in :func:`reproject`.
        history_length: (B, 1, H, W) frames accumulated into ``previous`` per pixel (0 or 1 for a
            single frame; zeros make the call return ``current`` with ``n = 1``).
        alpha: smallest weight of the current frame, reached after ``1 / alpha`` frames.

    Returns:
        ``(accumulated (B, C, H, W), history_length (B, 1, H, W))``: where the reprojection is
        valid, ``n = min(n_prev + 1, 1 / alpha)`` (``n_prev`` reprojected with the colour's taps)
        and ``out = a * current + (1 - a) * history`` with ``a = max(alpha, 1 / n)``; elsewhere
        ``n = 1`` and ``out = current``.  ``impl="reference"`` runs the per-pixel Python loop (tiny
        images only).

    A sequence: ``acc, n = noisy_0, ones``; then per frame
    ``acc, n = temporal_accumulate(noisy_t, acc, motion_t, ..., n)``; or use :class:`TemporalAccumulation`.
    """
    _check_all(current, previous, motion, position, prev_position, normal, prev_normal, history_length, alpha)
    if impl == "reference":
        return temporal_accumulate_reference(
            current, previous, motion, position, prev_position, normal, prev_normal, history_length, alpha,
            position_tolerance=position_tolerance, normal_cos=normal_cos,
        )
    if impl != "fast":
        raise ValueError(f"temporal: impl must be 'fast' or 'reference', got {impl!r}")
    c = current.shape[1]
    # The history length rides along as one more channel, so it gets exactly the colour's taps.
    both = torch.cat([previous, history_length.to(previous.dtype)], dim=1)
    history, valid = reproject(
        both, motion, position, prev_position, normal, prev_normal,
        position_tolerance=position_tolerance, normal_cos=normal_cos,
    )
    n = torch.where(valid, (history[:, c:] + 1).clamp(1.0, _cap(alpha)), torch.ones_like(history[:, c:]))
    a = history_alpha(n, alpha)
    out = torch.where(valid, a * current + (1 - a) * history[:, :c], current)
    return out, n


def temporal_accumulate_reference(
    current: torch.Tensor,
    previous: torch.Tensor,
    motion: torch.Tensor,
    position: torch.Tensor,
    prev_position: torch.Tensor,
    normal: torch.Tensor,
    prev_normal: torch.Tensor,
    history_length: torch.Tensor,
    alpha: float = 0.2,
    *,
    position_tolerance: float = 0.05,
    normal_cos: float = 0.9,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Plain per-pixel loop with the same semantics as :func:`temporal_accumulate` (tests only)."""
    _check_all(current, previous, motion, position, prev_position, normal, prev_normal, history_length, alpha)
    b, c, h, w = current.shape
    rows, lengths = [], []
    for bi in range(b):
        out_b, n_b = [], []
        for y in range(h):
            for x in range(w):
                sx = x - float(motion[bi, 0, y, x])
                sy = y - float(motion[bi, 1, y, x])
                x0, y0 = math.floor(sx), math.floor(sy)
                # Kept as tensors so gradients reach the motion vectors.
                fx = (x - motion[bi, 0, y, x].to(current.dtype)) - x0
                fy = (y - motion[bi, 1, y, x].to(current.dtype)) - y0
                num = current.new_zeros(c)
                n_num = current.new_zeros(())
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
                        n_num = n_num + wt * history_length[bi, 0, ty, tx].to(current.dtype)
                        wsum = wsum + wt
                cur = current[bi, :, y, x]
                if float(wsum) >= MIN_TAP_WEIGHT:
                    length = min(max(float(n_num / wsum) + 1, 1.0), _cap(alpha))
                    a = max(alpha, 1.0 / length)
                    out_b.append(a * cur + (1 - a) * num / wsum)
                    n_b.append(length)
                else:
                    out_b.append(cur)
                    n_b.append(1.0)
        rows.append(torch.stack(out_b, dim=-1).view(c, h, w))
        lengths.append(torch.tensor(n_b, dtype=current.dtype, device=current.device).view(1, h, w))
    return torch.stack(rows, dim=0), torch.stack(lengths, dim=0)


class TemporalAccumulation(nn.Module):
    """Stateful accumulation over a frame sequence, holding the blend floor and tolerances.

    ``forward(current, motion, position, normal)`` -> (B, C, H, W) accumulated frame; the first
    call (and the first after :meth:`reset`) returns ``current`` with history length 1.  The state
    (previous result, positions, normals, history lengths) is kept out of the state dict.
    """

    def __init__(self, alpha: float = 0.2, position_tolerance: float = 0.05, normal_cos: float = 0.9) -> None:
        super().__init__()
        self.alpha = alpha
        self.position_tolerance = position_tolerance
        self.normal_cos = normal_cos
        self._state: tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    def reset(self) -> None:
        """Forget the history (a cut in the sequence)."""
        self._state = None

    @property
    def history_length(self) -> torch.Tensor | None:
        """(B, 1, H, W) frames accumulated per pixel after the last call, or None after a reset."""
        return None if self._state is None else self._state[3]

    def forward(
        self, current: torch.Tensor, motion: torch.Tensor, position: torch.Tensor, normal: torch.Tensor
    ) -> torch.Tensor:
        if self._state is None:
            out, n = current, torch.ones_like(current[:, :1])
        else:
            prev, prev_pos, prev_n, length = self._state
            out, n = temporal_accumulate(
                current, prev, motion, position, prev_pos, normal, prev_n, length, self.alpha,
                position_tolerance=self.position_tolerance, normal_cos=self.normal_cos,
            )
        self._state = (out, position, normal, n)
        return out
