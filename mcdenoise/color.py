"""Colour constants shared by every stage (numpy only; torch tensors are handled without importing
torch): luminance of linear RGB with the Rec. 709 / sRGB weights."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["LUMINANCE_WEIGHTS", "luminance"]

#: Rec. 709 / sRGB luminance weights of linear R, G, B.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)


def luminance(rgb: Any, axis: int = -1, *, keepdims: bool = False) -> Any:
    """Luminance of linear RGB along ``axis`` (of length 3).

    numpy arrays: float64 weights (``rgb @ w`` for the last axis, ``tensordot`` otherwise), so the
    result is float64 for float32 input too. torch tensors: weights in the tensor's dtype and
    device, ``(rgb * w).sum(axis)``.
    """
    if rgb.shape[axis] != 3:
        raise ValueError(f"luminance: axis {axis} of shape {tuple(rgb.shape)} must have 3 (RGB) entries")
    if hasattr(rgb, "new_tensor"):  # a torch tensor
        shape = [1] * rgb.ndim
        shape[axis] = 3
        return (rgb * rgb.new_tensor(LUMINANCE_WEIGHTS).view(shape)).sum(dim=axis, keepdim=keepdims)
    w = np.array(LUMINANCE_WEIGHTS, dtype=np.float64)
    a = axis % rgb.ndim
    if a == rgb.ndim - 1:
        out = rgb @ w
    else:
        out = np.tensordot(w, np.moveaxis(rgb, a, 0), axes=1)
    return np.expand_dims(out, a) if keepdims else out
