"""Outdoor layouts: flat or hilly ground, an environment map or ``sunsky``, Poisson-disc objects
around the camera's view.
"""

from __future__ import annotations

import math

import numpy as np

from mcdenoise.render.procedural import meshes as pm
from mcdenoise.render.procedural import textures as pt
from mcdenoise.render.procedural.camera import _Camera, _roll_up
from mcdenoise.render.procedural.materials import _bitmap, _material
from mcdenoise.render.procedural.objects import MAX_OBJECTS, _Builder, _mesh, _random_object
from mcdenoise.render.procedural.seeds import _loguniform
from mcdenoise.render.procedural.transforms import _rotate, _scale, _xform

__all__ = []


def _poisson_disc(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, radius: float, limit: int) -> np.ndarray:
    """Dart-throwing Poisson-disc samples in the 2D box [lo, hi] (at most ``limit`` points)."""
    pts = np.empty((limit, 2))
    n = 0
    for p in rng.uniform(lo, hi, size=(limit * 30, 2)):
        if n == 0 or ((pts[:n] - p) ** 2).sum(axis=1).min() >= radius * radius:
            pts[n] = p
            n += 1
            if n >= limit:
                break
    return pts[:n]


def _outdoor(b: _Builder, n_objects: int) -> _Camera:
    rng = b.rng
    ground_mat = _material(rng, b.materials, b.textures, kind=str(rng.choice(["diffuse", "roughplastic", "principled"])))
    if rng.random() < 0.5:
        b.add("ground", {"type": "rectangle", "id": "ground", "to_world": _xform(_rotate([1, 0, 0], -np.pi / 2) @ _scale([200, 200, 1])), "bsdf": ground_mat})
    else:
        arrays = pm.terrain(rng, size=120.0, height=rng.uniform(2.0, 15.0))
        b.add("ground", _mesh(b, "ground", arrays, ground_mat))

    if rng.random() < 0.4:
        elev = rng.uniform(0.05, 1.3)
        az = rng.uniform(0, 2 * np.pi)
        b.add("sky", {
            "type": "sunsky", "id": "sky",
            "sun_direction": [math.cos(elev) * math.sin(az), math.sin(elev), -math.cos(elev) * math.cos(az)],
            "turbidity": float(rng.uniform(2.0, 8.0)), "sun_scale": 1.0, "sky_scale": 1.0,
            # Mitsuba's sunsky is Z-up; our world is Y-up. sun_direction is in world space
            # (checked: with this rotation a sun at +Y lights the sky above, none below).
            "to_world": _xform(_rotate([1, 0, 0], -np.pi / 2)),
        })
        b.textures["sunsky"] = 1
    else:
        style, img = pt.envmap_image(rng, 64, 128)
        b.textures[f"envmap_{style}"] = 1
        b.add("sky", {"type": "envmap", "id": "sky", "bitmap": _bitmap(img), "scale": 1.0,
                      "to_world": _xform(_rotate([0, 1, 0], rng.uniform(0, 2 * np.pi)))})
    b.emitters.append("sky")

    fov = float(rng.uniform(30, 70))
    cam_h = rng.uniform(0.5, 3.0)
    heading = rng.uniform(0, 2 * np.pi)
    fwd = np.array([math.sin(heading), 0.0, math.cos(heading)])
    side = np.array([fwd[2], 0.0, -fwd[0]])
    scale = _loguniform(rng, 0.3, 1.5)  # object size scale for this scene
    dist = rng.uniform(3.0, 10.0) * scale
    origin = np.array([0.0, cam_h, 0.0])
    # Poisson-disc candidate positions on the ground within and slightly beyond the frustum.
    half = math.tan(math.radians(fov) / 2) * 1.2
    depth_lo, depth_hi = 1.5 * scale, dist * 2.5
    pts = _poisson_disc(rng, np.array([depth_lo, -1.0]), np.array([depth_hi, 1.0]), rng.uniform(0.05, 0.15), MAX_OBJECTS * 3)
    cand = [origin * [1, 0, 1] + fwd * u + side * (v * half * u) for u, v in pts]
    rng.shuffle(cand)
    target = origin * [1, 0, 1] + fwd * dist + np.array([0.0, rng.uniform(0.0, 1.0) * scale, 0.0])
    cam = _Camera(origin, target, _roll_up(rng), fov)
    for i in range(min(n_objects, len(cand))):
        p = np.array(cand[i], float)
        # No object closer than 5 radii: one object filling the view makes a useless image.
        size = min(_loguniform(rng, 0.2, 1.0) * scale, float(np.linalg.norm(p - origin)) / 5)
        p[1] = size if rng.random() < 0.7 else size + rng.uniform(0, 2.0) * scale  # some float
        _random_object(b, f"object_{i}", p, size)
    return cam
