"""The drawn camera: position, target, up vector (with random roll), lens and sensor dict."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mcdenoise.render.procedural.objects import _Builder
from mcdenoise.render.procedural.seeds import _loguniform
from mcdenoise.render.procedural.transforms import _xform, look_at

__all__ = []


@dataclass
class _Camera:
    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float


def _sensor(b: _Builder, cam: _Camera, width: int, height: int, dof: bool) -> tuple[dict, float, float]:
    """Sensor dict; returns it with (aperture radius, focus distance)."""
    rng = b.rng
    to_world = look_at(cam.origin, cam.target, cam.up)
    d: dict = {
        "type": "perspective",
        "id": "camera",
        "fov": float(cam.fov),
        "fov_axis": "x",
        "to_world": _xform(to_world),
        "near_clip": 0.01,
        "far_clip": 10000.0,
        "film": {
            "type": "hdrfilm",
            "width": int(width),
            "height": int(height),
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
        "sampler": {"type": "independent", "sample_count": 4},
    }
    aperture, focus = 0.0, float(np.linalg.norm(cam.target - cam.origin))
    if dof:
        # Focus on the target or somewhere around it; aperture so that the circle of confusion of
        # objects at half/double the focus distance spans a few % of the image width.
        focus = focus * float(rng.uniform(0.6, 1.3))
        aperture = focus * math.tan(math.radians(cam.fov) / 2) * _loguniform(rng, 0.01, 0.08)
        d.update(type="thinlens", aperture_radius=float(aperture), focus_distance=float(focus))
    return d, aperture, focus


#: Blur radius of a point at infinity, as a fraction of the image's half-width, of a wide lens
#: (``strong_dof``): 3-19 px at 128 px, the shallow focus of product and portrait photography.
#: The ordinary lens above stops at 0.08 (5 px), below what a real shot at f/1.4-2.8 shows.
WIDE_LENS_BLUR = (0.05, 0.3)


def _wide_lens(d: dict, cam: _Camera, rng: np.random.Generator) -> tuple[float, float]:
    """Make the sensor dict ``d`` a thin lens with a wide aperture, drawn from ``rng`` alone (so
    every other draw of the scene stays as it was); returns (aperture radius, focus distance).

    Focus lands near the target (0.85-1.1 of its distance): the subject sharp, the rest blurred.
    A point at distance z is blurred to ``k |z - f| / z`` of the half-width, k drawn log-uniformly
    in :data:`WIDE_LENS_BLUR`: texture and edges behind and before the subject spread over
    several pixels, and each sample's first hit (albedo, normal) lands elsewhere on the lens.
    """
    focus = float(np.linalg.norm(cam.target - cam.origin)) * float(rng.uniform(0.85, 1.1))
    aperture = focus * math.tan(math.radians(cam.fov) / 2) * _loguniform(rng, *WIDE_LENS_BLUR)
    d.update(type="thinlens", aperture_radius=float(aperture), focus_distance=float(focus))
    return aperture, focus


def _roll_up(rng: np.random.Generator) -> np.ndarray:
    """An up vector near +Y: most cameras are level, some tilted (SBMC randomises the up vector)."""
    roll = rng.normal(0, 0.08) if rng.random() < 0.7 else rng.uniform(-0.6, 0.6)
    return np.array([math.sin(roll), math.cos(roll), 0.0])
