"""One kernel launch: trace a band of rows at some spp and bring the samples back to numpy,
either summed per pixel or reordered sample-major for the data format."""

from __future__ import annotations

from typing import Any, Collection, Mapping

import numpy as np

from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.integrator import FULL_OUTPUTS, LEVEL_FULL, LEVEL_REFERENCE
from mcdenoise.render.motion import _move_camera_rays
from mcdenoise.render.prepared import _Prepared


def _trace_chunk(
    scene: Any,
    prep: _Prepared,
    *,
    rows: slice,
    spp: int,
    seed: int,
    level: int,
    time_override: float | None,
    record_position: bool,
    reduce: bool,
    keep: Collection[str] | None = None,
    stack: tuple[int, Any] | None = None,
) -> dict[str, np.ndarray]:
    """Trace rows ``rows`` at ``spp`` samples per pixel.

    Returns name -> (spp, C, h, W) float32 per-sample arrays, or (C, h, W) float64 pixel sums when
    ``reduce``. ``keep`` (None = all) limits the outputs; the kernel then skips the others.

    ``stack`` = (H, M) renders several views of the scene in one launch: ``rows`` then index an
    image of V stacked views (V*H rows), and the rays of view ``v`` are the sensor's rays (its pose,
    its camera motion) moved by the rigid transform ``M[12v:12v+12]`` (the 3x4 rows of
    ``camera_v @ inverse(sensor camera)``, a Float array), see :mod:`mcdenoise.render.view_stack`.
    """
    mi = mitsuba()
    import drjit as dr

    W = prep.width
    y0, y1 = rows.start, rows.stop
    h = y1 - y0
    n = W * h * spp
    sampler = prep.sensor.sampler().fork()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(dr.opaque(mi.UInt32, seed & 0xFFFFFFFF), n)

    idx = dr.arange(mi.UInt32, n)
    if stack is None:
        idx //= dr.opaque(mi.UInt32, spp)
    else:
        # A stack orders its lanes (sample, row, column): the data format's sample-major planes
        # come back without a transpose (7% of an image's time at 128x128, 16 spp: docs/DATASETS.md).
        idx %= dr.opaque(mi.UInt32, W * h)
    py = idx // dr.opaque(mi.UInt32, W)
    px = idx - py * dr.opaque(mi.UInt32, W)
    py += dr.opaque(mi.UInt32, y0)
    view = None
    if stack is not None:
        view = py // dr.opaque(mi.UInt32, stack[0])
        py -= view * dr.opaque(mi.UInt32, stack[0])
    pos = mi.Vector2f(mi.Float(px), mi.Float(py))
    sub = sampler.next_2d()
    sample_pos = pos + sub
    scale = mi.ScalarVector2f(1.0 / W, 1.0 / prep.height)
    adjusted = dr.fma(sample_pos, scale, mi.ScalarVector2f(0.0, 0.0))
    aperture = mi.Point2f(0.5)
    if prep.has_lens:
        aperture = sampler.next_2d()
    t_ray = mi.Float(prep.shutter_open)
    t_norm = mi.Float(0.0)
    if prep.shutter_time > 0:
        u = sampler.next_1d()
        if time_override is not None:
            u = dr.opaque(mi.Float, float(time_override)) + 0.0 * u
        t_ray = t_ray + u * prep.shutter_time
        t_norm = u
    elif time_override is not None:
        t_norm = dr.opaque(mi.Float, float(time_override)) + mi.Float(0.0) * sub.x
    ray, ray_weight = prep.sensor.sample_ray_differential(t_ray, 0.0, adjusted, aperture)
    if ray.has_differentials:
        ray.scale_differential(dr.rsqrt(float(spp)))
    if prep.cam_start is not None:
        ray = _move_camera_rays(ray, t_norm, prep)
    if stack is not None:
        ray = _move_rays_to_views(ray, view, stack[1])
    out = prep.integrator.trace(scene, sampler, ray, mi.Bool(True), level)
    values: dict[str, Any] = {"radiance": ray_weight * out["radiance"]}
    if level >= LEVEL_REFERENCE:
        values["diffuse"] = ray_weight * out["diffuse"]
        values["specular"] = ray_weight * out["specular"]
        values["albedo"] = out["albedo"]
    if level >= LEVEL_FULL:
        for k in FULL_OUTPUTS:
            if k in values or k == "position" and not record_position:
                continue
            values[k] = out[k]
        values["subpixel"] = sub
        lens = mi.Vector2f(0.0)
        if prep.has_lens:
            lens = mi.warp.square_to_uniform_disk_concentric(aperture)
        values["lens"] = lens
        values["time"] = t_norm

    # Flatten every value into a list of Float components.
    comps: dict[str, list[Any]] = {}
    for k, v in values.items():
        if keep is not None and k not in keep:
            continue
        if isinstance(v, list):
            comps[k] = v
        elif isinstance(v, mi.Float):
            comps[k] = [v]
        else:
            comps[k] = [v[i] for i in range(len(v))]
    res: dict[str, np.ndarray] = {}
    flat = [c for cs in comps.values() for c in cs]
    dr.eval(*flat)
    if not reduce:
        return _sample_major(comps, spp=spp, h=h, W=W, lanes_sample_major=stack is not None)

    def host(c: Any) -> np.ndarray:
        a = np.asarray(c, dtype=np.float32).reshape(-1)
        # Constant outputs (e.g. no lens) come back as one literal: broadcast them.
        return np.full(n, a[0], dtype=np.float32) if a.size == 1 and n != 1 else a

    for k, cs in comps.items():
        # Summed here rather than with dr.block_sum, which is ~6x slower than the trace on LLVM.
        if stack is None:
            arr = np.stack([host(c).reshape(h * W, spp).sum(axis=1, dtype=np.float64) for c in cs], 0)
        else:
            arr = np.stack([host(c).reshape(spp, h * W).sum(axis=0, dtype=np.float64) for c in cs], 0)
        res[k] = arr.reshape(len(cs), h, W)
    return res


def _move_rays_to_views(ray: Any, view: Any, mats: Any) -> Any:
    """Apply per lane the rigid transform of the lane's view (rows of 3x4 matrices in ``mats``)."""
    mi = mitsuba()
    import drjit as dr

    m = [dr.gather(mi.Float, mats, view * 12 + k) for k in range(12)]

    def point(p: Any) -> Any:
        return mi.Point3f(*(m[4 * r] * p.x + m[4 * r + 1] * p.y + m[4 * r + 2] * p.z + m[4 * r + 3] for r in range(3)))

    def vector(d: Any) -> Any:
        return mi.Vector3f(*(m[4 * r] * d.x + m[4 * r + 1] * d.y + m[4 * r + 2] * d.z for r in range(3)))

    ray.o, ray.d = point(ray.o), dr.normalize(vector(ray.d))
    if ray.has_differentials:
        ray.o_x, ray.o_y = point(ray.o_x), point(ray.o_y)
        ray.d_x, ray.d_y = dr.normalize(vector(ray.d_x)), dr.normalize(vector(ray.d_y))
    return ray


def _sample_major(comps: Mapping[str, list[Any]], *, spp: int, h: int, W: int,
                  lanes_sample_major: bool = False) -> dict[str, np.ndarray]:
    """Reorder evaluated per-lane components into name -> (spp, C, h, W) float32 arrays
    (``lanes_sample_major``: the lanes are in (sample, row, column) order already, a view stack's).

    Lanes are ordered (row, column, sample) like ``mi.render``'s, because the sampler's random
    stream belongs to the lane index and the radiance must match ``mi.render`` bit for bit; the
    format wants sample-major planes, so numpy transposes each component. The destination is
    memory from Dr.Jit's allocation cache, already mapped by earlier renders: into fresh numpy
    arrays the first-touch page faults cost more than the copy itself (72 vs 13 ms at 256x256,
    8 spp on 2 cores). Tried and slower: scattering to sample-major order from inside the trace
    kernel (its time doubled: ~45 strided store streams per lane) and a Dr.Jit gather kernel.
    """
    n = spp * h * W
    res: dict[str, np.ndarray] = {}
    for k, cs in comps.items():
        arr = host_array((spp, len(cs), h, W))
        for i, c in enumerate(cs):
            a = np.asarray(c, dtype=np.float32).reshape(-1)
            if a.size == 1 and n != 1:
                arr[:, i] = a[0]  # constant output (e.g. no lens) comes back as one literal
            elif lanes_sample_major:
                arr[:, i] = a.reshape(spp, h, W)
            else:
                arr[:, i] = a.reshape(h, W, spp).transpose(2, 0, 1)
        res[k] = arr
    return res


#: Largest Dr.Jit array (sizes are 32-bit).
_MAX_JIT_WIDTH = 2**32 - 1


def host_array(shape: tuple[int, ...]) -> np.ndarray:
    """An uninitialised float32 array of ``shape``, taken from Dr.Jit's allocation cache where
    numpy can alias it (the LLVM backend): that memory is mapped already by earlier renders, while
    a fresh numpy array pays a page fault per 4 KiB on first touch, which cost more than the copy
    into it (:func:`_sample_major`). Elsewhere a plain ``np.empty``."""
    mi = mitsuba()
    import drjit as dr

    n = int(np.prod(shape))
    if dr.backend_v(mi.Float) == dr.JitBackend.LLVM and 0 < n <= _MAX_JIT_WIDTH:
        buf = dr.empty(mi.Float, n)
        dr.make_opaque(buf)  # allocate now; numpy's view keeps the buffer alive
        return np.asarray(buf).reshape(shape)
    return np.empty(shape, dtype=np.float32)


def _row_bands(width: int, height: int, spp: int, chunk_samples: int) -> list[slice]:
    rows = max(1, min(height, chunk_samples // max(1, width * spp)))
    return [slice(y, min(height, y + rows)) for y in range(0, height, rows)]

