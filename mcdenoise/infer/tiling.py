"""Run a model over an image of any size in overlapping tiles, with the same result as one call.

A tile is a *core* (the pixels it writes to the output) inside a *window* (the pixels the model
reads): the window extends the core by ``overlap`` pixels on every side, clipped to the image.
Tiling is exact (up to float rounding) when

* ``overlap`` >= the model's receptive field (:func:`mcdenoise.infer.receptive.receptive_field`):
  a core pixel then sees in its window everything it sees in the whole image, and nothing of the
  window's zero padding; and
* window origins and core sizes are multiples of the model's pooling alignment
  (:func:`mcdenoise.infer.receptive.alignment`), so 2x2 pooling groups the same pixels.

No model normalises per input (every per-image statistic -- depth range, maximum radiance -- was
replaced by fixed maps in the models for this reason; see ``wskp_input`` and ``kpcn_features``), so
nothing else can differ between a tile and the image. ``tests/test_tiling.py`` checks every
registered model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
import torch

from mcdenoise.models.registry import Denoiser

__all__ = ["Tile", "TilePlan", "plan_tiles", "run_tiled"]

#: (y0, x0, h, w) in image pixels.
Box = tuple[int, int, int, int]


@dataclass(frozen=True)
class Tile:
    """One tile: the ``window`` the model reads and the ``core`` it writes, both ``(y0, x0, h, w)``."""

    window: Box
    core: Box

    @property
    def core_in_window(self) -> tuple[slice, slice]:
        """Slices of the core within the window's output."""
        dy, dx = self.core[0] - self.window[0], self.core[1] - self.window[1]
        return slice(dy, dy + self.core[2]), slice(dx, dx + self.core[3])


@dataclass(frozen=True)
class TilePlan:
    """A grid of cores of side ``core`` (the last ones smaller) with ``overlap`` pixels of context."""

    height: int
    width: int
    core: int
    overlap: int

    @property
    def window(self) -> int:
        """Side of an interior tile's window."""
        return self.core + 2 * self.overlap

    def tiles(self) -> list[Tile]:
        out = []
        for y in range(0, self.height, self.core):
            for x in range(0, self.width, self.core):
                ch, cw = min(self.core, self.height - y), min(self.core, self.width - x)
                wy, wx = max(0, y - self.overlap), max(0, x - self.overlap)
                wh = min(self.height, y + ch + self.overlap) - wy
                ww = min(self.width, x + cw + self.overlap) - wx
                out.append(Tile((wy, wx, wh, ww), (y, x, ch, cw)))
        return out

    def __len__(self) -> int:
        return math.ceil(self.height / self.core) * math.ceil(self.width / self.core)


def plan_tiles(height: int, width: int, *, receptive: int, align: int = 1,
               core: int | None = None, max_window_pixels: int | None = None) -> TilePlan:
    """Choose the tile grid.

    Args:
        receptive: the model's receptive field radius; the overlap is this rounded up to ``align``.
        align: the model's pooling alignment; cores (hence window origins) are multiples of it.
        core: a fixed core side (``--tile N``), rounded up to ``align``; None: from the budget.
        max_window_pixels: largest window (pixels) that fits the memory budget. The image is one
            tile when it fits whole; otherwise the core is the largest aligned side whose window
            fits (at least ``align``: a budget below one minimal tile is exceeded, not refused).
    """
    overlap = math.ceil(receptive / align) * align
    if core is not None:
        if core < 1:
            raise ValueError(f"tile size must be positive, got {core}")
        side = math.ceil(core / align) * align
    elif max_window_pixels is None or height * width <= max_window_pixels:
        side = max(height, width)
    else:
        room = int(math.isqrt(max(0, max_window_pixels))) - 2 * overlap
        side = max(align, room // align * align)
    if side >= height and side >= width:
        overlap = 0  # one tile: nothing to overlap
    return TilePlan(height, width, max(1, side), overlap)


def run_tiled(
    model: Denoiser,
    read: Callable[[Tile], dict[str, torch.Tensor]],
    plan: TilePlan,
    *,
    progress: Callable[[Iterable[Tile]], Iterable[Tile]] | None = None,
) -> np.ndarray:
    """Denoise tile by tile: ``read(tile)`` gives the model's batch (of one) for ``tile.window``.

    Returns the ``(3, H, W)`` output (numpy, on the host: only one tile's output is ever on the
    device): float64 when the model runs in float64 (tests compare tiles in the precision whose
    rounding does not depend on the CPU's kernels), else float32.
    """
    out: np.ndarray | None = None
    tiles: Iterable[Tile] = plan.tiles()
    if progress is not None:
        tiles = progress(tiles)
    # inference mode, as the bench's bare call: no version counters (issue 18: API within 10%)
    with torch.inference_mode():
        for tile in tiles:
            batch = read(tile)
            y = model(batch)
            del batch
            sy, sx = tile.core_in_window
            cy, cx, ch, cw = tile.core
            want = torch.float64 if y.dtype == torch.float64 else torch.float32
            if len(plan) == 1 and (ch, cw) == (plan.height, plan.width) and y.shape[-2:] == (ch, cw):
                # one tile is the image: hand its output over instead of copying it into a new one
                return np.ascontiguousarray(y[0].to(want).cpu().numpy())
            if out is None:
                out = np.zeros((3, plan.height, plan.width), np.float64 if want == torch.float64 else np.float32)
            out[:, cy : cy + ch, cx : cx + cw] = y[0, :, sy, sx].to(want).cpu().numpy()
            del y
    assert out is not None  # a plan always has at least one tile
    return out
