"""The Cycles render settings of docs/DENOISE.md's Blender 4.x recipe, and ours for reproducibility.

Used by the dataset worker and by the slow Blender tests' scenes (``tests/blender_scenes.py``), so
both render the same way.
"""

from __future__ import annotations

from typing import Any

__all__ = ["apply_recipe"]


def apply_recipe(scene: Any, out: str, *, spp: int, size: int, seed: int, threads: int = 1,
                 blender_denoise: bool = False, light_passes: bool = False, max_bounces: int = 8) -> None:
    """Set ``scene`` (a ``bpy.types.Scene``) to render ``size`` x ``size`` at ``spp`` to ``out``.

    The recipe: Cycles, *Denoising Data* on, OpenEXR MultiLayer, 32-bit float. Ours: CPU, a fixed
    seed and thread count, no adaptive sampling, no clamping, caustics on (the noise a user's
    default render has, and a file that is the same on any machine with the same Blender).
    ``light_passes`` also writes Diffuse/Glossy/Transmission Direct, Indirect and Color,
    Emission and Environment: the split kpcn reads (:func:`mcdenoise.io.blender.light_split`).
    """
    scene.render.engine = "CYCLES"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.image_settings.color_depth = "32"
    scene.view_layers[0].cycles.denoising_store_passes = True
    scene.cycles.use_denoising = blender_denoise
    scene.render.filepath = out
    scene.cycles.device = "CPU"
    scene.cycles.samples = spp
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.seed = seed
    scene.cycles.max_bounces = max_bounces
    scene.cycles.transmission_bounces = max_bounces
    scene.cycles.caustics_reflective = True
    scene.cycles.caustics_refractive = True
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    scene.cycles.denoising_use_gpu = False
    scene.render.threads_mode = "FIXED"
    scene.render.threads = threads
    scene.render.resolution_x = scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    if light_passes:
        layer = scene.view_layers[0]
        for kind in ("diffuse", "glossy", "transmission"):
            for part in ("direct", "indirect", "color"):
                setattr(layer, f"use_pass_{kind}_{part}", True)
        layer.use_pass_emit = layer.use_pass_environment = True
