"""Rendering with Mitsuba 3: per-sample data, references, built-in scenes.

Importing this package does not import Mitsuba; the first render does (see ``_mitsuba``).
"""

from mcdenoise.render.api import (
    REFERENCE_CHANNELS,
    SAMPLE_CHANNELS,
    RenderSettings,
    builtin_motion,
    iter_sample_chunks,
    list_builtin_scenes,
    load_scene,
    render_image,
    render_reference,
    render_samples,
    scene_features,
    stream_seed,
)

__all__ = [
    "REFERENCE_CHANNELS",
    "SAMPLE_CHANNELS",
    "RenderSettings",
    "builtin_motion",
    "iter_sample_chunks",
    "list_builtin_scenes",
    "load_scene",
    "render_image",
    "render_reference",
    "render_samples",
    "scene_features",
    "stream_seed",
]
