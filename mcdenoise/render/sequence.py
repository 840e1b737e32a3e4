"""Frame sequences: a smooth camera path, pinhole projection and screen-space motion vectors.

WSKP's temporal accumulation (:mod:`mcdenoise.ops.temporal`) reprojects the previous frame's
output with per-pixel motion vectors. Conventions (as in :mod:`mcdenoise.data.channels` and the
temporal op): ``motion`` is in pixels from the previous frame to this one, pixel centres sit on
integer coordinates, so the current pixel ``(x, y)`` was at ``(x - motion_x, y - motion_y)``.

Motion is computed geometrically, not from the renders: the ray through each pixel centre of the
current camera (pinhole, lens centre) is intersected with the scene; the hit point (or, for a miss,
the direction at infinity) is projected into the previous camera. Both cameras use Mitsuba's
``perspective`` model: camera-to-world with local +Z forward, +Y up, +X to the *left*, horizontal
field of view ``fov`` (``fov_axis="x"``), film x growing to the right and y downwards.

Frames of a sequence have a static scene (no object motion between frames); motion blur within a
frame, if any, is the renderer's business.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "camera_path",
    "pixel_rays",
    "project",
    "primary_hits",
    "motion_vectors",
]


def _look_at(origin: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    from mcdenoise.render.procedural import look_at

    return look_at(origin, target, up)


def _catmull_rom(p: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Uniform Catmull-Rom spline through control points ``p`` (K, 3) at ``t`` in [0, 1] -> (T, 3).

    The curve passes through p[1] .. p[K-2]; p[0] and p[K-1] only shape the tangents. Its first
    derivative is continuous, so the camera never jerks between frames.
    """
    segs = len(p) - 3
    s = np.clip(t, 0.0, 1.0) * segs
    i = np.minimum(s.astype(int), segs - 1)
    u = (s - i)[:, None]
    p0, p1, p2, p3 = p[i], p[i + 1], p[i + 2], p[i + 3]
    return 0.5 * (
        2 * p1 + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u**2 + (-p0 + 3 * p1 - 3 * p2 + p3) * u**3
    )


def camera_path(
    origin: Any,
    target: Any,
    up: Any,
    frames: int,
    rng: np.random.Generator,
    *,
    max_shift: float | None = None,
) -> list[np.ndarray]:
    """``frames`` camera-to-world matrices along a smooth random path around a view.

    The camera starts at ``origin`` and moves along a Catmull-Rom spline through control points
    within ``max_shift`` of it (default: 15% of the distance to ``target``); the target drifts by a
    third of that, so the view turns a little too.
    """
    o = np.asarray(origin, float)
    tg = np.asarray(target, float)
    u = np.asarray(up, float)
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    dist = float(np.linalg.norm(tg - o))
    shift = 0.15 * dist if max_shift is None else float(max_shift)
    k = 5  # control points: 2 shaping tangents + 3 the path passes through (2 segments)
    cp_o = o + rng.uniform(-1, 1, (k, 3)) * shift
    cp_o[1] = o  # the path starts exactly at the drawn view
    cp_t = tg + rng.uniform(-1, 1, (k, 3)) * shift / 3
    cp_t[1] = tg
    t = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    path_o = _catmull_rom(cp_o, t)
    path_t = _catmull_rom(cp_t, t)
    return [_look_at(a, b, u) for a, b in zip(path_o, path_t)]


def _tan_half(fov_x: float) -> float:
    if not 0.0 < fov_x < 180.0:
        raise ValueError(f"fov must be in (0, 180) degrees, got {fov_x}")
    return math.tan(math.radians(fov_x) / 2)


def pixel_rays(camera_to_world: np.ndarray, fov_x: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays through the pixel centres of a pinhole camera -> origins (H, W, 3), unit dirs (H, W, 3)."""
    m = np.asarray(camera_to_world, float)
    th = _tan_half(fov_x)
    aspect = width / height
    y, x = np.mgrid[0:height, 0:width]
    sx = (x + 0.5) / width
    sy = (y + 0.5) / height
    local = np.stack([(1 - 2 * sx) * th, (1 - 2 * sy) * th / aspect, np.ones_like(sx, dtype=float)], -1)
    d = local @ m[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    o = np.broadcast_to(m[:3, 3], d.shape).copy()
    return o, d


def project(
    points: np.ndarray, camera_to_world: np.ndarray, fov_x: float, width: int, height: int, *, directions: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Film coordinates (continuous pixels, (0, 0) = top-left corner) of world points (..., 3).

    Where ``directions`` (bool, points.shape[:-1]) is True the vector is a direction at infinity
    (only the camera rotation applies). Returns ``(xy (..., 2), in_front (...))``; points behind
    the camera get NaN coordinates and ``in_front`` False.
    """
    m = np.asarray(camera_to_world, float)
    r = m[:3, :3]
    p = np.asarray(points, float)
    rel = p - m[:3, 3]
    if directions is not None:
        rel = np.where(np.asarray(directions)[..., None], p, rel)
    # Inverse of an orthonormal-ish camera matrix: solve, so a scaled camera still projects right.
    local = np.linalg.solve(r, rel.reshape(-1, 3).T).T.reshape(rel.shape)
    th = _tan_half(fov_x)
    aspect = width / height
    z = local[..., 2]
    front = z > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        sx = 0.5 * (1 - local[..., 0] / (z * th))
        sy = 0.5 * (1 - local[..., 1] * aspect / (z * th))
    xy = np.stack([sx * width, sy * height], -1)
    xy[~front] = np.nan
    return xy, front


def primary_hits(scene: Any, camera_to_world: np.ndarray, fov_x: float, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersect the pixel-centre rays with a loaded Mitsuba scene.

    Returns ``(position (H, W, 3), hit (H, W) bool, direction (H, W, 3))``; position is 0 on a miss.
    """
    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    o, d = pixel_rays(camera_to_world, fov_x, width, height)
    ray = mi.Ray3f(mi.Point3f(*[o[..., i].ravel().astype(np.float32) for i in range(3)]),
                   mi.Vector3f(*[d[..., i].ravel().astype(np.float32) for i in range(3)]))
    si = scene.ray_intersect(ray)
    hit = np.array(si.is_valid()).reshape(height, width)
    pos = np.stack([np.array(si.p[i]) for i in range(3)], -1).reshape(height, width, 3).astype(np.float64)
    pos[~hit] = 0.0
    return pos, hit, d


def motion_vectors(
    position: np.ndarray,
    hit: np.ndarray,
    direction: np.ndarray,
    prev_camera_to_world: np.ndarray,
    fov_x: float,
    width: int,
    height: int,
) -> np.ndarray:
    """Screen-space motion (2, H, W) float32 in pixels, previous -> current frame.

    ``position``/``hit``/``direction`` describe the current frame's pixel-centre hits (see
    :func:`primary_hits`); misses are reprojected as directions at infinity. Pixels whose point is
    behind the previous camera get motion 0 (no usable history; the temporal op's position test
    rejects them anyway).
    """
    h, w = hit.shape
    pts = np.where(hit[..., None], position, direction)
    prev_xy, front = project(pts, prev_camera_to_world, fov_x, width, height, directions=~hit)
    y, x = np.mgrid[0:h, 0:w]
    cur = np.stack([x + 0.5, y + 0.5], -1)
    mv = cur - prev_xy
    mv[~front] = 0.0
    return np.ascontiguousarray(mv.transpose(2, 0, 1), dtype=np.float32)
