""":class:`ProceduralScene`: one drawn scene, its Mitsuba dict and what the renderer needs beside it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["ProceduralScene"]


@dataclass
class ProceduralScene:
    """One drawn scene: the Mitsuba dict and what the renderer needs to know beside it.

    Attributes:
        scene: Mitsuba 3 scene dict (for ``mi.load_dict``); procedural meshes are ``mi.Mesh``
            objects inside it, shared (not copied) by every scene loaded from it. Drop it when
            done: Dr.Jit compiles virtual calls to every live BSDF in the process, so drawn scenes
            kept alive make every later kernel compile slower.
        seed: the seed given to :func:`generate`.
        drawn_seed: the seed that produced the accepted scene (differs after rejections).
        attempts: how many drawings were rejected before this one.
        kind: ``"indoor"`` or ``"outdoor"``.
        camera_to_world: 4x4 camera matrix at shutter open (Mitsuba convention, +Z forward).
        fov: horizontal field of view in degrees.
        aperture_radius, focus_distance: thin-lens parameters (aperture 0 = pinhole).
        depth_of_field, motion_blur: which distributed effects are on.
        shutter: (open, close) times of the shutter.
        camera_to_world_end: camera matrix at shutter close when the camera moves, else None.
        object_motion: shape id -> world translation (3,) over the shutter, linear in time.
        camera_path: (origin, target, up) used to build sequences around this view.
        info: summary for meta.json: material/texture/shape kinds counted, object and light count,
            preview statistics, emitter scale applied, rejected drawings.
        extents: shape id -> (centre (3,), radius) of every random object and furniture piece,
            so that other views keep clear of them and motion can be measured on screen.
        room: indoor scenes: (half width along x, half depth along z, height); None outdoors.
        loaded: the Mitsuba scene loaded at the film size, camera made opaque and emitters
            already rescaled, when :func:`generate` was asked to keep it (else None). Rendering
            this very object again reuses the kernels its preview compiled; a second load of the
            same dict (while this one lives) would compile them all again.
    """

    scene: dict
    seed: int
    drawn_seed: int
    attempts: int
    kind: str
    camera_to_world: np.ndarray
    fov: float
    aperture_radius: float
    focus_distance: float
    depth_of_field: bool
    motion_blur: bool
    shutter: tuple[float, float]
    camera_to_world_end: np.ndarray | None
    object_motion: dict[str, list[float]]
    camera_path: tuple[np.ndarray, np.ndarray, np.ndarray]
    info: dict
    extents: dict[str, tuple[np.ndarray, float]] = field(default_factory=dict)
    room: tuple[float, float, float] | None = None
    loaded: Any = None
