"""Motion blur: posing moving objects at a shutter time, stratified time slices, and moving
camera rays between the start and end camera transforms."""

from __future__ import annotations

from typing import Any

import numpy as np

from mcdenoise.errors import SceneError
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.prepared import _Prepared
from mcdenoise.render.seeds import stream_seed


def _pose_objects(prep: _Prepared, t: float) -> None:
    """Move every animated shape to normalised shutter time ``t`` (0 = the scene as loaded)."""
    mi = mitsuba()
    for key, (base, tr) in prep.motion.items():
        if key.endswith(".to_world"):
            m = base.copy()
            m[:3, 3] += tr * t
            prep.params[key] = mi.Transform4f(m.tolist())
        else:
            prep.params[key] = mi.Float((base + tr * t).astype(np.float32).reshape(-1))
            if key in prep.normals:
                # New vertex positions alone make Mitsuba recompute the vertex normals from the
                # faces: a moved mesh then shades with other normals than the loaded one (0.12
                # apart on a procedural mesh), and the recomputation sums with atomics, so
                # reference renders differed run to run (~1e-6). A translation keeps the
                # normals: hand the loaded ones back (a fresh array, else the update skips it).
                nkey, normals = prep.normals[key]
                prep.params[nkey] = mi.Float(normals)
    prep.params.update()


def _rotation_parts(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Split an affine camera transform into a proper rotation, translation and a mirror flag."""
    r = m[:3, :3].copy()
    flip = np.linalg.det(r) < 0
    if flip:
        r[:, 0] = -r[:, 0]
    # Remove any scale so the quaternion is well defined.
    u, _, vt = np.linalg.svd(r)
    return u @ vt, m[:3, 3].copy(), bool(flip)


def _quat(r: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) of a rotation matrix."""
    tr = np.trace(r)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
        q = [0.0, 0.0, 0.0, 0.0]
        q[i] = 0.25 * s
        q[j] = (r[j, i] + r[i, j]) / s
        q[k] = (r[k, i] + r[i, k]) / s
        q[3] = (r[k, j] - r[j, k]) / s
    return np.asarray(q, dtype=np.float64)


def _move_camera_rays(ray: Any, t: Any, prep: _Prepared) -> Any:
    """Re-pose rays generated at the start transform to the camera at normalised time ``t``."""
    mi = mitsuba()
    import drjit as dr

    r0, p0, flip0 = _rotation_parts(prep.cam_start)
    r1, p1, flip1 = _rotation_parts(prep.cam_end)
    if flip0 != flip1:
        raise SceneError("camera motion: start and end transforms differ in handedness")
    q0, q1 = _quat(r0), _quat(r1)
    if np.dot(q0, q1) < 0:
        q1 = -q1
    inv_start = mi.Transform4f(np.linalg.inv(prep.cam_start).tolist())
    # Every number of the two camera poses reaches the kernel as an opaque value: as literals,
    # each view of a scene with camera motion compiled its own kernels (2 s at 64x64, measured),
    # and the values are the same either way (renders bit-identical, tested).
    dr.make_opaque(inv_start)

    def opaque(x: float) -> Any:
        return dr.opaque(mi.Float, float(x))

    # Per-lane normalised-lerp of the rotation (nlerp is within 0.1% of slerp for the small
    # turns of a shutter interval and is cheap), lerp of the translation.
    q = [opaque(a) * (1.0 - t) + opaque(b) * t for a, b in zip(q0, q1)]
    n = dr.rsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    x, y, z, w = (c * n for c in q)
    rot = mi.Matrix3f(
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    )
    trans = mi.Vector3f(*[opaque(a) for a in p0]) * (1.0 - t) + mi.Vector3f(*[opaque(b) for b in p1]) * t
    sign = mi.Vector3f(-1.0 if flip0 else 1.0, 1.0, 1.0)

    def point(p: Any) -> Any:
        local = inv_start @ mi.Point3f(p)
        return mi.Point3f(rot @ (mi.Vector3f(local) * sign) + trans)

    def vector(v: Any) -> Any:
        local = inv_start @ mi.Vector3f(v)
        return dr.normalize(rot @ (mi.Vector3f(local) * sign))

    ray.o = point(ray.o)
    ray.d = vector(ray.d)
    if ray.has_differentials:
        ray.o_x, ray.o_y = point(ray.o_x), point(ray.o_y)
        ray.d_x, ray.d_y = vector(ray.d_x), vector(ray.d_y)
    return ray



def _slice_times(seed: int, spp: int) -> np.ndarray:
    """Stratified slice times (s + u_s) / S, one per sample index."""
    rng = np.random.default_rng(stream_seed(seed, 0x51CE))
    return (np.arange(spp) + rng.random(spp)) / spp

