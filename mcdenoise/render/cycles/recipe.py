"""The Cycles render settings of docs/DENOISE.md's Blender recipes, and ours for reproducibility.

Used by the dataset worker and by the slow Blender tests' scenes (``tests/blender_scenes.py``), so
both render the same way. No import of mcdenoise's dependencies: a Blender Python (bpy 5.x needs
Python 3.13) loads this file by its path.

Blender 4.x writes every enabled pass of a render into an OpenEXR MultiLayer file. Blender 5.x
writes only ``Combined`` there, so the passes go through the compositor instead
(:func:`route_passes`): a File Output node in multi-layer EXR mode with one input per pass, named
as Blender 4 names them in its files (``Combined``, ``Noisy Image``, ``Denoising Albedo``...,
``DiffDir``...), which is what :mod:`mcdenoise.io.blender` reads. Blender 5 writes such a file with
one part per pass and no view-layer prefix; the reader takes both layouts.
"""

from __future__ import annotations

from typing import Any

__all__ = ["BLENDER5_PASS_NAMES", "apply_recipe", "route_passes"]

#: Render Layers socket (Blender 5) -> the pass name Blender 4 writes in a multi-layer EXR.
BLENDER5_PASS_NAMES = {
    "Image": "Combined", "Noisy Image": "Noisy Image", "Denoising Albedo": "Denoising Albedo",
    "Denoising Normal": "Denoising Normal", "Denoising Depth": "Denoising Depth",
    "Diffuse Direct": "DiffDir", "Diffuse Indirect": "DiffInd", "Diffuse Color": "DiffCol",
    "Glossy Direct": "GlossDir", "Glossy Indirect": "GlossInd", "Glossy Color": "GlossCol",
    "Transmission Direct": "TransDir", "Transmission Indirect": "TransInd", "Transmission Color": "TransCol",
    "Emission": "Emit", "Environment": "Env",
}


def route_passes(scene: Any, out: str, *, color_depth: str = "32") -> None:
    """Blender 5.x: write every pass of :data:`BLENDER5_PASS_NAMES` the view layer has to ``out``
    (OpenEXR MultiLayer, ``color_depth`` "32" or "16") through a compositor File Output node.
    Render with ``bpy.ops.render.render(write_still=False)``: the node writes the file."""
    import os

    import bpy

    scene.render.compositor_device = "CPU"  # a headless machine has no GPU context for it
    tree = bpy.data.node_groups.new("mcdenoise passes", "CompositorNodeTree")
    scene.compositing_node_group = tree
    layers = tree.nodes.new("CompositorNodeRLayers")
    node = tree.nodes.new("CompositorNodeOutputFile")
    node.format.media_type = "MULTI_LAYER_IMAGE"
    node.format.color_depth = color_depth
    stem, ext = os.path.splitext(os.path.abspath(out))
    node.directory, node.file_name = os.path.dirname(stem) + os.sep, os.path.basename(stem)
    node.use_file_extension = ext.lower() == ".exr"
    node.file_output_items.clear()
    for socket in layers.outputs:
        name = BLENDER5_PASS_NAMES.get(socket.name)
        if name is None or not socket.enabled:
            continue
        kind = {"VALUE": "FLOAT", "VECTOR": "VECTOR"}.get(socket.type, "RGBA")
        node.file_output_items.new(kind, name)
        tree.links.new(socket, node.inputs[name])


def apply_recipe(scene: Any, out: str, *, spp: int, size: int, seed: int, threads: int = 1,
                 blender_denoise: bool = False, light_passes: bool = False, max_bounces: int = 8,
                 half: bool = False) -> bool:
    """Set ``scene`` (a ``bpy.types.Scene``) to render ``size`` x ``size`` at ``spp`` to ``out``.

    The recipe: Cycles, *Denoising Data* on, OpenEXR MultiLayer, 32-bit float. Ours: CPU, a fixed
    seed and thread count, no adaptive sampling, no clamping, caustics on (the noise a user's
    default render has, and a file that is the same on any machine with the same Blender).
    ``light_passes`` also writes Diffuse/Glossy/Transmission Direct, Indirect and Color,
    Emission and Environment: the split kpcn reads (:func:`mcdenoise.io.blender.light_split`).
    ``half``: 16-bit float passes. Returns ``write_still`` for ``bpy.ops.render.render``: True on
    Blender 4.x; False on 5.x, where :func:`route_passes` writes the file.
    """
    import bpy

    blender5 = bpy.app.version >= (5, 0, 0)
    scene.render.engine = "CYCLES"
    if blender5:
        scene.render.image_settings.media_type = "MULTI_LAYER_IMAGE"
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    scene.render.image_settings.color_depth = "16" if half else "32"
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
    if blender5:
        route_passes(scene, out, color_depth="16" if half else "32")
    return not blender5
