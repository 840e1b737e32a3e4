"""The converged reference image (radiance, diffuse, specular, albedo), with seeds independent
of the per-sample input's."""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from mcdenoise.errors import SceneError
from mcdenoise.render.integrator import LEVEL_REFERENCE
from mcdenoise.render.motion import _pose_objects, _slice_times
from mcdenoise.render.prepare import _prepare, _restore
from mcdenoise.render.seeds import stream_seed
from mcdenoise.render.settings import REFERENCE_CHANNELS, RenderSettings
from mcdenoise.render.trace import _row_bands, _trace_chunk

__all__ = ["render_reference"]


def render_reference(
    scene: Any,
    settings: RenderSettings,
    *,
    seed: int | None = None,
    camera_to_world: np.ndarray | None = None,
    spp: int | None = None,
    progress: Callable[[int], None] | None = None,
    stack: tuple[Sequence[np.ndarray], np.ndarray] | None = None,
) -> Any:
    """Reference image: name -> (C, H, W) float32 for radiance, diffuse, specular, albedo.

    ``progress`` is called with the number of camera samples traced after each chunk.

    Seeds are derived from ``seed`` under a key the per-sample input never uses, so reference and
    input noise are independent. Object motion is resolved with ``spp`` stratified time slices.

    ``stack`` = (cameras, sensor camera) renders the references of several views of the scene in
    one stack (:mod:`mcdenoise.render.view_stack`; the sensor must be posed at the sensor camera)
    and returns one such dict per camera; time slices are then shared by the views.
    """
    seed = settings.seed if seed is None else int(seed)
    spp = settings.ref_spp if spp is None else int(spp)
    if spp < 1:
        raise SceneError(f"render settings: reference spp={spp} must be >= 1")
    prep = _prepare(scene, settings, camera_to_world)
    W, V = settings.width, 1
    traced: Any = None
    if stack is not None:
        from mcdenoise.render._mitsuba import mitsuba
        from mcdenoise.render.view_stack import check_sampler, view_transforms

        check_sampler(scene)
        V = len(stack[0])
        traced = (settings.height, mitsuba().Float(view_transforms(stack[1], stack[0])))
    H = settings.height * V  # the views' rows, stacked
    sums: dict[str, np.ndarray] = {}
    try:
        if settings.object_motion:
            # One slice per pass; slices stratify the shutter, so the reference converges to the
            # motion-blurred image like the input does.
            n_slices = min(spp, settings.ref_time_slices)
            per = [spp // n_slices + (1 if i < spp % n_slices else 0) for i in range(n_slices)]
            times = _slice_times(stream_seed(seed, 3), n_slices)
            passes = [(float(t), k, i) for i, (t, k) in enumerate(zip(times, per))]
        else:
            per_pass = max(1, min(spp, settings.chunk_samples // max(1, W * H)))
            passes = []
            left, i = spp, 0
            while left > 0:
                k = min(per_pass, left)
                passes.append((None, k, i))
                left -= k
                i += 1
        for t, k, i in passes:
            if t is not None:
                _pose_objects(prep, t)
            bands = _row_bands(W, H, k, settings.chunk_samples)
            for b, rows in enumerate(bands):
                out = _trace_chunk(scene, prep, rows=rows, spp=k, seed=stream_seed(seed, 4, i, b), level=LEVEL_REFERENCE,
                                   time_override=t, record_position=False, reduce=True, stack=traced)
                for name, v in out.items():
                    if name not in sums:
                        sums[name] = np.zeros((v.shape[0], H, W), dtype=np.float64)
                    sums[name][:, rows] += v
                if progress is not None:
                    progress(k * (rows.stop - rows.start) * W)
    finally:
        _restore(scene, prep)
    h = settings.height
    refs = [{k: (sums[k][:, v * h:(v + 1) * h] / spp).astype(np.float32) for k in REFERENCE_CHANNELS} for v in range(V)]
    return refs if stack is not None else refs[0]
