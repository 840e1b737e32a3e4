"""Test-time self-ensemble: a model run on the 8 symmetries of the square (D4) of its input, each
output turned back, and the per-pixel median of the 8 kept.

Why it helps: every network here was trained on crops in all 8 orientations
(:mod:`mcdenoise.train.augment`), so each orientation of an image is an equally good estimate, with
errors that are partly independent. Why the median and not the mean: one orientation can explode a
highlight that the other seven do not (on one held-out image a single pass's relMSE ranged from
0.056 to 518 across the 8); the mean keeps an eighth of it, the median drops it (docs/TRAINING.md,
campaign 20).

How a batch turns: every image tensor (``(B, C, H, W)`` pixels or ``(B, S, C, H, W)`` samples) moves
with its pixels; film directions (``lens``, ``motion``) take the op's 2x2 matrix ``M``, ``subpixel``
turns about the pixel centre, and their variances swap components (``M`` is a signed permutation).
World-space normals and positions are left as they are: without a camera frame that is still an
exact rendering of the turned scene, in a turned world frame the networks cannot tell from the
original (:mod:`mcdenoise.train.augment`). Non-image entries (``scene_features``, an exposure scale)
are passed through.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np
import torch

from mcdenoise.data.channels import base_name, is_variance_name
from mcdenoise.data.symmetry import FILM_VECTORS, NUM_OPS, SUBPIXEL, film_matrix, inverse_op, spatial

__all__ = ["ALL_OPS", "turn_tensor", "transform_batch", "untransform", "median_of", "self_ensemble"]

#: Every op, identity first.
ALL_OPS: tuple[int, ...] = tuple(range(NUM_OPS))


def turn_tensor(x: torch.Tensor, op: int) -> torch.Tensor:
    """:func:`mcdenoise.data.symmetry.spatial` for a tensor ``(..., H, W)`` (any H, W; contiguous)."""
    film_matrix(op)  # range check
    k, flip = op % 4, op // 4
    if flip:
        x = x.flip(-1)
    if k:
        x = torch.rot90(x, k, dims=(-2, -1))
    return x.contiguous()


def _film_vector(name: str, x: torch.Tensor, op: int) -> torch.Tensor:
    """Apply ``M`` (``M*M`` to a variance) to the component axis (-3) of ``(..., 2, H, W)``."""
    m = torch.as_tensor(film_matrix(op), dtype=x.dtype, device=x.device)
    if is_variance_name(name):
        return torch.einsum("ij,...jhw->...ihw", m * m, x)
    if base_name(name) == SUBPIXEL:
        return torch.einsum("ij,...jhw->...ihw", m, x - 0.5) + 0.5
    return torch.einsum("ij,...jhw->...ihw", m, x)


def transform_batch(batch: Mapping[str, torch.Tensor], op: int) -> dict[str, torch.Tensor]:
    """A model's batch as the image turned by op would give it (see the module docstring)."""
    if op == 0:
        return dict(batch)
    out: dict[str, torch.Tensor] = {}
    for name, x in batch.items():
        if not isinstance(x, torch.Tensor) or x.dim() < 4:  # scene features, exposure scale: not images
            out[name] = x
            continue
        if base_name(name) in FILM_VECTORS or base_name(name) == SUBPIXEL:
            x = _film_vector(name, x, op)
        out[name] = turn_tensor(x, op)
    return out


def untransform(y: np.ndarray, op: int) -> np.ndarray:
    """An output ``(..., h, w)`` of the turned batch, turned back to the image's frame."""
    return spatial(y, inverse_op(op), square=False)


def median_of(outputs: Sequence[np.ndarray]) -> np.ndarray:
    """Per-element median of equally shaped outputs (the mean of the middle two for an even count),
    in their dtype."""
    if len(outputs) == 1:
        return outputs[0]
    stack = np.stack(outputs)
    return np.median(stack, axis=0).astype(stack.dtype, copy=False)


def self_ensemble(run: Callable[[dict[str, torch.Tensor]], np.ndarray], batch: Mapping[str, torch.Tensor],
                  ops: Sequence[int] = ALL_OPS) -> np.ndarray:
    """The per-pixel median over ``ops`` of ``run`` (batch -> ``(3, H, W)`` numpy) on the turned
    batch, each output turned back: ``(3, H, W)``."""
    return median_of([untransform(run(transform_batch(batch, op)), op) for op in ops])
