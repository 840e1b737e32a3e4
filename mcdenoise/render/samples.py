"""Per-sample renders: the whole image as arrays, or streamed band by band (bounded memory)."""

from __future__ import annotations

from typing import Any, Iterator

import numpy as np

from mcdenoise.render.integrator import LEVEL_FULL
from mcdenoise.render.motion import _pose_objects, _slice_times
from mcdenoise.render.prepare import _prepare, _restore
from mcdenoise.render.scene_loading import scene_features
from mcdenoise.render.seeds import stream_seed
from mcdenoise.render.settings import RenderSettings
from mcdenoise.render.trace import _row_bands, _trace_chunk

__all__ = ["iter_sample_chunks", "render_samples"]


def iter_sample_chunks(
    scene: Any,
    settings: RenderSettings,
    *,
    seed: int | None = None,
    camera_to_world: np.ndarray | None = None,
    record_position: bool = False,
    time_slices: bool | None = None,
) -> Iterator[tuple[slice, slice, dict[str, np.ndarray]]]:
    """Render per-sample data piece by piece: yields ``(samples, rows, arrays)`` with arrays
    name -> (s, C, h, W) float32. Memory stays bounded by ``settings.chunk_samples``.

    ``time_slices`` (default: on when ``settings.object_motion``) renders one sample index per
    pass with the scene posed at that index's stratified time.
    """
    seed = settings.seed if seed is None else int(seed)
    prep = _prepare(scene, settings, camera_to_world)
    channels = settings.sample_channels()
    keep = set(channels) | ({"position"} if record_position else set())
    slices = bool(settings.object_motion) if time_slices is None else bool(time_slices)
    W, H, S = settings.width, settings.height, settings.spp
    try:
        if not slices:
            bands = _row_bands(W, H, S, settings.chunk_samples)
            for i, rows in enumerate(bands):
                # One band: the seed itself, so that the result equals mi.render at that seed.
                s = seed if len(bands) == 1 else stream_seed(seed, 1, i)
                out = _trace_chunk(scene, prep, rows=rows, spp=S, seed=s, level=LEVEL_FULL, time_override=None,
                                   record_position=record_position, reduce=False, keep=keep)
                yield slice(0, S), rows, out
        else:
            times = _slice_times(seed, S)
            bands = _row_bands(W, H, 1, settings.chunk_samples)
            for si, t in enumerate(times):
                _pose_objects(prep, float(t))
                for i, rows in enumerate(bands):
                    out = _trace_chunk(scene, prep, rows=rows, spp=1, seed=stream_seed(seed, 2, si, i), level=LEVEL_FULL,
                                       time_override=float(t), record_position=record_position, reduce=False, keep=keep)
                    yield slice(si, si + 1), rows, out
    finally:
        _restore(scene, prep)


def render_samples(
    scene: Any,
    settings: RenderSettings,
    *,
    seed: int | None = None,
    time_slices: bool | None = None,
    camera_to_world: np.ndarray | None = None,
    record_position: bool = False,
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Per-sample data of the whole image: name -> (S, C, H, W) float32, and the scene features.

    ``position`` (world position of the first hit, per sample) is added when ``record_position``.
    """
    S, H, W = settings.spp, settings.height, settings.width
    arrays: dict[str, np.ndarray] = {}
    for samples, rows, chunk in iter_sample_chunks(
        scene, settings, seed=seed, camera_to_world=camera_to_world, record_position=record_position, time_slices=time_slices
    ):
        if samples == slice(0, S) and rows.start == 0 and rows.stop == H and not arrays:
            arrays = chunk  # the whole image in one piece: no copy
            continue
        for k, v in chunk.items():
            if k not in arrays:
                arrays[k] = np.zeros((S, v.shape[1], H, W), dtype=np.float32)
            arrays[k][samples, :, rows] = v
    feats = scene_features(scene)
    return arrays, feats

