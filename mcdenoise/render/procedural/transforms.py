"""4x4 transform matrices (numpy, Y up, metres) and their Mitsuba form."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mcdenoise.render._mitsuba import mitsuba

__all__ = ["look_at"]


def _translate(t: Any) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _scale(s: Any) -> np.ndarray:
    return np.diag([*np.broadcast_to(np.asarray(s, float), (3,)), 1.0])


def _rotate(axis: Any, angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    return m


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return m


def look_at(origin: Any, target: Any, up: Any) -> np.ndarray:
    """Camera-to-world 4x4 with Mitsuba's convention: local +Z forward, +Y up, +X to the left."""
    o = np.asarray(origin, float)
    d = np.asarray(target, float) - o
    d /= np.linalg.norm(d)
    left = np.cross(np.asarray(up, float), d)
    n = np.linalg.norm(left)
    if n < 1e-9:  # up parallel to the view direction: pick any perpendicular
        left = np.cross([1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 0.0, 1.0], d)
        n = np.linalg.norm(left)
    left /= n
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m



def _xform(m: np.ndarray) -> Any:
    return mitsuba().ScalarTransform4f(np.asarray(m, np.float64).tolist())
