"""Several camera views of one loaded scene in one kernel launch: per-sample data of a stack of views.

A view of a scene with moving objects renders its input as one time slice per sample index, each
slice a scene update and a kernel launch whose fixed cost (40-50 ms for Mitsuba's scene update,
35-40 ms to trace the integrator again in Python, ~15 ms to assemble the kernel) was 3-4x the
slice's rendering at 128x128 (docs/DATASETS.md, "Speed"). Views that share the slice times share
each pose: here every slice is posed once and traced once for all views, their rays stacked as the
rows of one tall image (V views of H rows = V*H rows), each view's rays moved from the sensor's
camera to their own by a rigid transform (:func:`~mcdenoise.render.trace._move_rays_to_views`).
A static scene gets the same stacking, in bands of at most ``settings.chunk_samples`` lanes.

The lanes of a stack draw their random numbers by their place in the stack, so a view rendered in
a stack is not the image the same view gives alone (same distribution, other samples): a stack is
deterministic given its views and seed, and the procedural dataset re-renders a scene's whole
stack to resume any of its views (generator 4, :mod:`mcdenoise.render.procedural_image`).
"""

from __future__ import annotations

from typing import Any, Iterator, Sequence

import numpy as np

from mcdenoise.errors import SceneError
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.integrator import LEVEL_FULL
from mcdenoise.render.motion import _pose_objects, _slice_times
from mcdenoise.render.prepare import _prepare, _restore
from mcdenoise.render.seeds import stream_seed
from mcdenoise.render.settings import RenderSettings
from mcdenoise.render.trace import _row_bands, _trace_chunk, host_array

__all__ = ["check_sampler", "iter_view_stack", "render_view_stack", "view_transforms"]


def view_transforms(sensor_camera: np.ndarray, cameras: Sequence[np.ndarray]) -> np.ndarray:
    """(V*12,) float32: the 3x4 rows of ``camera_v @ inverse(sensor_camera)`` for each view.

    Raises SceneError when a camera is not a finite rigid 4x4 transform (a scaled or sheared
    camera would bend the rays' lengths, which the depth and position features rely on).
    """
    base = np.asarray(sensor_camera, dtype=np.float64)
    inv = np.linalg.inv(base)
    out = []
    for i, c in enumerate(cameras):
        c = np.asarray(c, dtype=np.float64)
        if c.shape != (4, 4) or not np.all(np.isfinite(c)):
            raise SceneError(f"view {i}: expected a finite 4x4 camera matrix, got shape {c.shape}")
        m = c @ inv
        r = m[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-4):
            raise SceneError(f"view {i}: camera relative to the sensor's is not rigid (scale or shear)")
        out.append(m[:3, :4].reshape(-1))
    return np.concatenate(out).astype(np.float32)


def check_sampler(scene: Any) -> None:
    """A stack orders its lanes (sample, row, column), which only a sampler whose lanes are
    interchangeable accepts: Mitsuba's ``independent``. SceneError for any other."""
    text = str(scene.sensors()[0].sampler())
    if not text.startswith("IndependentSampler"):
        raise SceneError(f"view stacks need the scene's sampler to be 'independent', not {text.split('[')[0]}")


def iter_view_stack(
    scene: Any,
    settings: RenderSettings,
    cameras: Sequence[np.ndarray],
    sensor_camera: np.ndarray,
    *,
    seed: int,
) -> Iterator[tuple[int, slice, slice, dict[str, np.ndarray]]]:
    """Render per-sample data of every view in ``cameras`` (4x4 each) of ``scene``, whose sensor is
    posed at ``sensor_camera`` (and moves as ``settings.camera_to_world_end`` says: each view gets
    the same motion in its own camera space).

    Yields ``(view, samples, rows, arrays)`` with arrays name -> (s, C, h, W) float32 for the
    view's own rows; the scene is left posed as loaded. With ``settings.object_motion``, sample
    index ``s`` of every view is rendered with the scene posed at the stack's slice time ``s``.
    """
    mi = mitsuba()
    V, W, H, S = len(cameras), settings.width, settings.height, settings.spp
    if V < 1:
        raise SceneError("a view stack needs at least one camera")
    mats = mi.Float(view_transforms(sensor_camera, cameras))
    check_sampler(scene)
    prep = _prepare(scene, settings, None)
    keep = set(settings.sample_channels())
    stack = (H, mats)

    def pieces(rows: slice, out: dict[str, np.ndarray]) -> Iterator[tuple[int, slice, dict[str, np.ndarray]]]:
        """Cut a band of stacked rows at the view boundaries."""
        y = rows.start
        while y < rows.stop:
            v = y // H
            stop = min(rows.stop, (v + 1) * H)
            a, b = y - rows.start, stop - rows.start
            yield v, slice(y - v * H, stop - v * H), {k: arr[:, :, a:b] for k, arr in out.items()}
            y = stop

    try:
        if not settings.object_motion:
            bands = _row_bands(W, V * H, S, settings.chunk_samples)
            for i, rows in enumerate(bands):
                out = _trace_chunk(scene, prep, rows=rows, spp=S, seed=stream_seed(seed, 1, i), level=LEVEL_FULL,
                                   time_override=None, record_position=False, reduce=False, keep=keep, stack=stack)
                for v, vrows, chunk in pieces(rows, out):
                    yield v, slice(0, S), vrows, chunk
        else:
            bands = _row_bands(W, V * H, 1, settings.chunk_samples)
            for si, t in enumerate(_slice_times(seed, S)):
                _pose_objects(prep, float(t))
                for i, rows in enumerate(bands):
                    out = _trace_chunk(scene, prep, rows=rows, spp=1, seed=stream_seed(seed, 2, si, i), level=LEVEL_FULL,
                                       time_override=float(t), record_position=False, reduce=False, keep=keep, stack=stack)
                    for v, vrows, chunk in pieces(rows, out):
                        yield v, slice(si, si + 1), vrows, chunk
    finally:
        _restore(scene, prep)


def render_view_stack(
    scene: Any,
    settings: RenderSettings,
    cameras: Sequence[np.ndarray],
    sensor_camera: np.ndarray,
    *,
    seed: int,
) -> list[dict[str, np.ndarray]]:
    """:func:`iter_view_stack` gathered: per view, name -> (S, C, H, W) float32 (in memory: the
    caller bounds the stack, e.g. ``procedural_image.STACK_BYTES``)."""
    S, H, W = settings.spp, settings.height, settings.width
    out: list[dict[str, np.ndarray]] = [{} for _ in cameras]
    whole = (slice(0, S), slice(0, H))
    for v, samples, rows, chunk in iter_view_stack(scene, settings, cameras, sensor_camera, seed=seed):
        for k, a in chunk.items():
            if (samples, slice(rows.start, rows.stop)) == whole and k not in out[v]:
                # The view lies whole in one band (a static scene's usual case): keep the band's
                # rows as they are. Copying them into fresh arrays cost 0.14 s of a 1.1 s image at
                # 128x128, 16 spp, mostly the new pages' first-touch faults (docs/DATASETS.md).
                out[v][k] = a
                continue
            if k not in out[v]:  # every sample and row of it is written below, by the view's pieces
                out[v][k] = host_array((S, a.shape[1], H, W))
            out[v][k][samples, :, rows] = a
    return out
