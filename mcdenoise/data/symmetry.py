"""The 8 symmetries of the square (dihedral group D4) acting on images: the pixel moves and the
2x2 matrix they apply to film directions.

``op = k + 4 * flip`` first mirrors the image left-right when ``flip``, then turns it ``k`` quarter
turns the way ``numpy.rot90(a, k, axes=(-2, -1))`` does. Training augments crops with them
(:mod:`mcdenoise.train.augment`); inference averages a model over them
(:mod:`mcdenoise.models.symmetry`). Both read the convention from here, so a crop a network was
trained on and an image it is run on are turned the same way.
"""

from __future__ import annotations

import numpy as np

__all__ = ["NUM_OPS", "FILM_VECTORS", "SUBPIXEL", "film_matrix", "spatial", "inverse_op", "turned_shape", "source_box"]

NUM_OPS = 8
#: Channels holding 2D film directions (``lens``: camera-space disk point; ``motion``: film pixels):
#: an op applies ``M`` to them. ``subpixel`` (position in the pixel, [0, 1)^2) turns about the pixel centre.
FILM_VECTORS = frozenset({"lens", "motion"})
SUBPIXEL = "subpixel"
_FLIP = np.array([[-1, 0], [0, 1]], np.int64)
# numpy.rot90 (axes=(-2, -1)) sends the film point (X, Y) of an n x n image to (Y, n - X).
_QUARTER = np.array([[0, 1], [-1, 0]], np.int64)


def _check(op: int) -> None:
    if not 0 <= op < NUM_OPS:
        raise ValueError(f"symmetry op must be in 0..{NUM_OPS - 1}, got {op}")


def film_matrix(op: int) -> np.ndarray:
    """``(2, 2)`` int matrix ``M`` of op on film directions ``(x right, y down)``."""
    _check(op)
    k, flip = op % 4, op // 4
    m = _FLIP if flip else np.eye(2, dtype=np.int64)
    return np.linalg.matrix_power(_QUARTER, k) @ m


def spatial(arr: np.ndarray, op: int, *, square: bool = True) -> np.ndarray:
    """Move the pixels of ``(..., h, w)`` by op (a contiguous copy). ``square``: refuse a quarter
    turn of a non-square array (a training crop must keep its shape); a whole image may turn to
    ``(..., w, h)``."""
    _check(op)
    k, flip = op % 4, op // 4
    if square and k % 2 and arr.shape[-1] != arr.shape[-2]:
        raise ValueError(f"a quarter turn needs a square crop, got {arr.shape[-2]}x{arr.shape[-1]}")
    out = arr[..., ::-1] if flip else arr
    return np.ascontiguousarray(np.rot90(out, k, axes=(-2, -1)))


def inverse_op(op: int) -> int:
    """The op that undoes ``op``: ``k`` turns back for a rotation; a mirror (``flip``) is its own inverse."""
    _check(op)
    k, flip = op % 4, op // 4
    return op if flip else (4 - k) % 4


def turned_shape(height: int, width: int, op: int) -> tuple[int, int]:
    """``(h, w)`` of an ``height x width`` image after op (a quarter turn swaps them)."""
    _check(op)
    return (width, height) if op % 2 else (height, width)


def _forward_pixel(y: int, x: int, height: int, width: int, op: int) -> tuple[int, int]:
    """Where pixel ``(y, x)`` of an ``height x width`` image lands after op."""
    k, flip = op % 4, op // 4
    if flip:
        x = width - 1 - x
    for _ in range(k):  # numpy.rot90 once: out[i, j] = in[j, w - 1 - i], shape (w, h)
        y, x, height, width = width - 1 - x, y, width, height
    return y, x


def source_box(box: tuple[int, int, int, int], op: int, height: int, width: int) -> tuple[int, int, int, int]:
    """The ``(y0, x0, h, w)`` box of the ``height x width`` image whose pixels op moves onto ``box``
    of the turned image (op maps boxes onto boxes: ``spatial(image[source_box], op)`` is
    ``spatial(image, op)[box]``)."""
    th, tw = turned_shape(height, width, op)
    y0, x0, h, w = box
    inv = inverse_op(op)
    a = _forward_pixel(y0, x0, th, tw, inv)
    b = _forward_pixel(y0 + h - 1, x0 + w - 1, th, tw, inv)
    return min(a[0], b[0]), min(a[1], b[1]), abs(a[0] - b[0]) + 1, abs(a[1] - b[1]) + 1
