"""Random indoor and outdoor scenes for training sets (SBMC Sec. 4.1, layer paper Sec. 4).

:func:`generate` draws one scene from a seed and returns a :class:`ProceduralScene`: a Mitsuba 3
scene dict (``mi.load_dict`` input, Y up, metres) plus what the renderer and the dataset need to
know about it (camera matrix, depth of field, motion). :func:`generate_scene` returns only the dict.

Everything is drawn from ``numpy.random.default_rng(seed)``: the same seed gives the same dict
(compare with :func:`scene_digest`) and, rendered with the same render seed, the same pixels. A drawn
scene is checked with a cheap preview (:func:`preview_stats`; the dataset renders it on the loaded
scene with the input's own settings, so that it compiles the kernel the input reuses): scenes that
render (nearly) black, show (almost) none of their objects or produce non-finite values are
re-drawn from a seed derived from ``(seed, attempt)``; the accepted scene's emitters are then
rescaled so that its median luminance lands in a random but sane range (so that training images
are neither black nor blown out).

What varies, per scene:

* kind: ``indoor`` (a box room, 1-5 pieces of furniture-like boxes, 1-5 area (ceiling disks,
  glowing spheres), point and spot lights)
  or ``outdoor`` (a flat or hilly ground, lit by a procedural HDR environment map or Mitsuba's
  ``sunsky``);
* 10-50 random objects: built-in ``sphere``/``cube``/``cylinder`` and procedural meshes
  (:mod:`.meshes`), with random scale, rotation and placement (outdoor: Poisson-disc positions
  within and slightly beyond the view; never too close to the camera);
* materials from :data:`MATERIALS` with textures from :data:`TEXTURES` and random UV scales, bump
  maps on some;
* camera: field of view, position, target, roll; thin-lens depth of field with probability 1/2;
  motion blur with probability 1/2 (linear motion of half the objects, and with probability 1/2
  also a camera motion).

The modules, in the order a scene goes through them (each imports only those above it):

=================  ==========================================================================
``seeds``          :func:`derive_seed` and seeded random choices
``transforms``     4x4 matrices (:func:`look_at`) and their Mitsuba form
``textures``       texture images and HDR environment maps (numpy)
``meshes``         procedural triangle meshes (numpy -> ``mi.Mesh``)
``materials``      random textures and BSDF dicts (:data:`MATERIALS`, :data:`TEXTURES`)
``objects``        the scene builder and random objects (shape table, object counts)
``camera``         the drawn camera and its sensor dict
``indoor``         room layouts: walls, furniture, objects, lights
``outdoor``        ground, sky, Poisson-disc objects
``scene``          :class:`ProceduralScene`
``draw``           one unchecked drawing: layout, lens, motion (:data:`KINDS`)
``loading``        :func:`load_procedural`
``preview``        the rejection check (:func:`preview_stats`, :class:`PreviewStats`)
``exposure``       emitter scaling of a dict
``views``          reuse of a loaded scene: opaque camera, other views, emitters rescaled in place
``generator``      :func:`generate`: draw, check, re-draw, expose
``digest``         :func:`scene_digest`
=================  ==========================================================================

Datasets of these scenes: :mod:`mcdenoise.render.procedural_dataset`.
"""

from __future__ import annotations

from mcdenoise.render.procedural.digest import scene_digest
from mcdenoise.render.procedural.draw import KINDS, _draw
from mcdenoise.render.procedural.exposure import _scale_emitters
from mcdenoise.render.procedural.generator import MAX_ATTEMPTS, generate, generate_scene
from mcdenoise.render.procedural.loading import load_procedural
from mcdenoise.render.procedural.materials import CONDUCTORS, MATERIALS, TEXTURES
from mcdenoise.render.procedural.objects import MAX_OBJECTS, MIN_OBJECTS, SHAPES
from mcdenoise.render.procedural.preview import PREVIEW_SIZE, PREVIEW_SPP, PreviewStats, preview_stats
from mcdenoise.render.procedural.scene import ProceduralScene
from mcdenoise.render.procedural.seeds import derive_seed
from mcdenoise.render.procedural.transforms import look_at

__all__ = [
    "KINDS",
    "MATERIALS",
    "TEXTURES",
    "SHAPES",
    "CONDUCTORS",
    "MIN_OBJECTS",
    "MAX_OBJECTS",
    "MAX_ATTEMPTS",
    "PREVIEW_SIZE",
    "PREVIEW_SPP",
    "ProceduralScene",
    "PreviewStats",
    "derive_seed",
    "generate",
    "generate_scene",
    "preview_stats",
    "load_procedural",
    "scene_digest",
    "look_at",
]
