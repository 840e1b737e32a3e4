"""Render per-sample data and references with Mitsuba 3.

The per-sample path generates all ``W*H*S`` camera rays itself and consumes the sampler in the
order ``mi.render`` does (sub-pixel 2D, aperture 2D when the sensor has a lens, time 1D when it has
a shutter, then the integrator), so the per-pixel mean of the samples equals ``mi.render`` with a
box filter and our ``mcdenoise_path`` integrator at the same seed and spp, whenever the image fits
in one chunk (:attr:`RenderSettings.chunk_samples`). Larger images are rendered in row bands with
seeds derived per band (still unbiased, no longer identical to one ``mi.render`` call).

Distributed effects:

* depth of field: any Mitsuba ``thinlens`` sensor; the lens position is recorded per sample.
* camera motion: ``camera_to_world_end``; every ray is moved to its own time (exact per sample).
* object motion: ``object_motion`` (shape id -> translation over the shutter). Mitsuba 3 has no
  moving shapes, so sample index ``s`` of every pixel is rendered with the scene posed at one
  stratified time ``(s + u_s) / S`` (``u_s`` from the seed): one time slice per sample index.

Seeds, times and sizes reach the kernels as opaque values, so a new seed or time never recompiles.

Where each concern lives (this module re-exports the public names, so ``mcdenoise.render.api``
imports keep working):

* :mod:`~mcdenoise.render.settings`: :class:`RenderSettings`, channel lists;
* :mod:`~mcdenoise.render.seeds`: ``stream_seed`` (the renderer's streams) and ``derive_seed`` (scenes);
* :mod:`~mcdenoise.render.scene_loading`: ``load_scene`` at a film size, built-in scenes, features;
* :mod:`~mcdenoise.render.prepare`: integrator + sensor set-up and restore around a render;
* :mod:`~mcdenoise.render.motion`: object poses, time slices, moving camera rays;
* :mod:`~mcdenoise.render.trace`: one kernel launch and the sample-major reordering;
* :mod:`~mcdenoise.render.samples`: per-sample renders (whole, or streamed in bands);
* :mod:`~mcdenoise.render.reference`: the reference image;
* :mod:`~mcdenoise.render.image`: ``render_image``, one image folder on disk.
"""

from __future__ import annotations

from mcdenoise.render.image import render_image
from mcdenoise.render.reference import render_reference
from mcdenoise.render.samples import iter_sample_chunks, render_samples
from mcdenoise.render.scene_loading import builtin_motion, list_builtin_scenes, load_scene, scene_features
from mcdenoise.render.settings import (
    MAX_SIZE,
    MAX_SPP,
    REFERENCE_CHANNELS,
    SAMPLE_CHANNELS,
    RenderSettings,
)
from mcdenoise.render.seeds import stream_seed

__all__ = [
    "RenderSettings",
    "SAMPLE_CHANNELS",
    "REFERENCE_CHANNELS",
    "list_builtin_scenes",
    "builtin_motion",
    "load_scene",
    "scene_features",
    "render_samples",
    "iter_sample_chunks",
    "render_reference",
    "render_image",
    "stream_seed",
    "MAX_SIZE",
    "MAX_SPP",
]
