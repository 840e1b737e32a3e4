"""Seeds and seeded random choices of the scene generator.

Every random number of a scene comes from one ``numpy.random.default_rng(seed)``; seeds of
re-drawn scenes, views and previews are derived from integers with :func:`derive_seed` (no clock;
defined in :mod:`mcdenoise.render.seeds` beside the renderer's ``stream_seed``).
"""

from __future__ import annotations

import math

import numpy as np

from mcdenoise.render.seeds import derive_seed

__all__ = ["derive_seed"]


def _choice(rng: np.random.Generator, table: dict[str, float]) -> str:
    keys = list(table)
    p = np.array([table[k] for k in keys])
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
