"""The one rule for NaN/Inf in image data: refuse with a report, or sanitise with a warning."""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence

import numpy as np

from mcdenoise.data.channels import CHANNELS, base_name, get_channel
from mcdenoise.errors import FormatError, NonFiniteError

__all__ = ["check_finite", "sanitize_nonfinite", "NONFINITE_POLICIES"]


def check_finite(
    name: str,
    arr: np.ndarray,
    path: str | os.PathLike,
    *,
    sanitize: bool = False,
    offset: tuple[int, int] = (0, 0),
    sample_index: Sequence[int] | None = None,
) -> np.ndarray:
    """Refuse (or, with ``sanitize``, zero with a warning) NaN/Inf in ``arr``.

    ``arr`` is ``(C, H, W)`` or ``(S, C, H, W)``; the report names the count and the first bad
    location in full-image coordinates (``offset`` = crop origin ``(y0, x0)``).
    """
    bad = ~np.isfinite(arr)
    n = int(bad.sum())
    if n == 0:
        return arr
    n_nan = int(np.isnan(arr).sum())
    first = np.unravel_index(int(np.argmax(bad)), arr.shape)
    comps = get_channel(name).components if base_name(name) in CHANNELS else None
    parts = []
    if arr.ndim == 4:
        s = first[0] if sample_index is None else sample_index[first[0]]
        parts.append(f"sample {s}")
        first = first[1:]
    c, y, x = (int(v) for v in first)
    parts.append(f"component {comps[c] if comps and c < len(comps) else c}")
    parts.append(f"pixel (y={y + offset[0]}, x={x + offset[1]})")
    msg = (f"channel {name!r}: {n} non-finite value(s) ({n_nan} NaN, {n - n_nan} Inf), "
           f"first at {', '.join(parts)}")
    if not sanitize:
        raise FormatError(path, msg + "; render the image again (`mcdenoise render`/`dataset` replace them by 0 "
                                      "with --nonfinite sanitize, the default), or read it with sanitize=True in Python")
    warnings.warn(f"{os.fspath(path)}: {msg}; replaced by 0", stacklevel=3)
    out = arr.copy()
    out[bad] = 0
    return out


#: Values of ``--nonfinite``: ``sanitize`` replaces NaN/Inf by 0 and warns with the count;
#: ``error`` refuses the data in one line.
NONFINITE_POLICIES = ("sanitize", "error")


def sanitize_nonfinite(arr: np.ndarray, policy: str, where: str | os.PathLike, what: str = "data") -> tuple[np.ndarray, int]:
    """The one rule for NaN/Inf shared by the renderer, the readers and ``denoise``.

    Rule: every NaN, +Inf and -Inf becomes 0 (a pixel with no usable estimate contributes
    nothing, and 0 is valid in every channel of the vocabulary); finite values are untouched.
    With ``policy="error"`` any non-finite value raises :class:`~mcdenoise.errors.NonFiniteError`
    naming ``where``, ``what`` and the count. Returns ``(array, count)``; the array is ``arr``
    itself when nothing was replaced, else a copy. The caller warns once with the total count.
    """
    if policy not in NONFINITE_POLICIES:
        raise ValueError(f"nonfinite policy {policy!r} is not one of {NONFINITE_POLICIES}")
    bad = ~np.isfinite(arr)
    n = int(np.count_nonzero(bad))
    if n == 0:
        return arr, 0
    if policy == "error":
        n_nan = int(np.count_nonzero(np.isnan(arr)))
        raise NonFiniteError(where, f"{what}: {n} non-finite value(s) ({n_nan} NaN, {n - n_nan} Inf); "
                                    "pass --nonfinite sanitize to replace them by 0")
    out = np.array(arr, copy=True)
    out[bad] = 0
    return out, n
