"""Built-in scenes, made by the project (Mitsuba 3 scene dicts built on demand).

Each entry has a description, a builder ``build(mi, width, height) -> dict`` and the motion it
carries (object translations and a camera end transform), which Mitsuba 3 scenes cannot express.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import ModuleType
from typing import Any, Callable

__all__ = ["BuiltinScene", "BUILTIN_SCENES"]


@dataclass(frozen=True)
class BuiltinScene:
    """A scene made by the project.

    Attributes:
        name: the name ``mcdenoise render`` accepts.
        description: one line for ``--list``.
        build: ``build(mi, width, height) -> dict`` for ``mi.load_dict``.
        object_motion: shape id -> world translation over the shutter interval.
        camera_to_world_end: 4x4 camera-to-world at shutter close (None = static camera).
    """

    name: str
    description: str
    build: Callable[[ModuleType, int, int], dict[str, Any]]
    object_motion: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    camera_to_world_end: tuple[tuple[float, ...], ...] | None = None


def _film(width: int, height: int) -> dict[str, Any]:
    # Box filter: per-pixel means of our samples then equal mi.render bit for bit.
    return {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}, "pixel_format": "rgb"}


def _cornell(mi: ModuleType, width: int, height: int) -> dict[str, Any]:
    d = mi.cornell_box()
    d["sensor"]["film"] = _film(width, height)
    d["sensor"]["sampler"] = {"type": "independent", "sample_count": 16}
    d["integrator"] = {"type": "mcdenoise_path", "max_depth": 6}
    return d


def _cornell_box(mi: ModuleType, width: int, height: int) -> dict[str, Any]:
    d = _cornell(mi, width, height)
    # A rough metal and a glass sphere give the specular buffers something to hold.
    d["metal"] = {"type": "roughconductor", "material": "Au", "alpha": 0.15}
    d["glass"] = {"type": "dielectric", "int_ior": 1.5}
    d["metal-sphere"] = {"type": "sphere", "center": [-0.45, -0.75, 0.35], "radius": 0.25, "bsdf": {"type": "ref", "id": "metal"}}
    d["glass-sphere"] = {"type": "sphere", "center": [0.45, -0.3, 0.45], "radius": 0.22, "bsdf": {"type": "ref", "id": "glass"}}
    return d


def _checker(mi: ModuleType, c0: list[float], c1: list[float], scale: float) -> dict[str, Any]:
    return {
        "type": "checkerboard",
        "color0": {"type": "rgb", "value": c0},
        "color1": {"type": "rgb", "value": c1},
        "to_uv": mi.ScalarTransform4f().scale([scale, scale, 1.0]),
    }


def _cornell_dof(mi: ModuleType, width: int, height: int) -> dict[str, Any]:
    d = _cornell(mi, width, height)
    d.pop("small-box")
    d.pop("large-box")
    sensor = d["sensor"]
    d["sensor"] = {
        "type": "thinlens",
        "fov": 39.3077,
        "aperture_radius": 0.12,
        "focus_distance": 3.9,
        "to_world": sensor["to_world"],
        "film": _film(width, height),
        "sampler": {"type": "independent", "sample_count": 16},
    }
    d["tex-near"] = {"type": "diffuse", "reflectance": _checker(mi, [0.8, 0.8, 0.1], [0.1, 0.1, 0.6], 8.0)}
    d["tex-far"] = {"type": "roughplastic", "alpha": 0.2, "diffuse_reflectance": _checker(mi, [0.9, 0.9, 0.9], [0.2, 0.6, 0.2], 6.0)}
    # Three spheres at different depths: near (blurred), at focus, far (blurred).
    d["near-sphere"] = {"type": "sphere", "center": [-0.4, -0.6, 1.6], "radius": 0.25, "bsdf": {"type": "ref", "id": "tex-near"}}
    d["focus-sphere"] = {"type": "sphere", "center": [0.1, -0.55, 0.0], "radius": 0.3, "bsdf": {"type": "ref", "id": "tex-far"}}
    d["far-sphere"] = {"type": "sphere", "center": [0.5, -0.6, -0.75], "radius": 0.3, "bsdf": {"type": "roughconductor", "material": "Cu", "alpha": 0.1}}
    return d


def _cornell_motion(mi: ModuleType, width: int, height: int) -> dict[str, Any]:
    d = _cornell(mi, width, height)
    d["sensor"]["shutter_open"] = 0.0
    d["sensor"]["shutter_close"] = 1.0
    # Own BSDFs keep Mitsuba from merging the moving shapes with static ones (merging drops ids).
    d["moving-box"] = {
        "type": "cube",
        "to_world": mi.ScalarTransform4f().translate([-0.35, 0.25, 0.2]).scale(0.18),
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.3, 0.8]}},
    }
    d["moving-sphere"] = {
        "type": "sphere",
        "center": [0.3, 0.4, -0.1],
        "radius": 0.15,
        "bsdf": {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": [0.8, 0.5, 0.1]}},
    }
    return d


def _camera_end() -> tuple[tuple[float, ...], ...]:
    # Cornell camera (looking down -z from z=3.9), moved 0.25 to the side and slightly turned.
    import math

    a = math.radians(4.0)
    c, s = math.cos(a), math.sin(a)
    # to_world = [[-1,0,0,0],[0,1,0,0],[0,0,-1,3.9]] rotated about y by a, translated in x.
    return (
        (-c, 0.0, -s, 0.25),
        (0.0, 1.0, 0.0, 0.0),
        (s, 0.0, -c, 3.9),
        (0.0, 0.0, 0.0, 1.0),
    )


BUILTIN_SCENES: dict[str, BuiltinScene] = {
    s.name: s
    for s in (
        BuiltinScene("cornell-box", "Cornell box with two boxes, a rough gold sphere and a glass sphere", _cornell_box),
        BuiltinScene(
            "cornell-dof",
            "Cornell box seen through a thin lens (aperture 0.12, focus 3.9) with textured spheres at three depths",
            _cornell_dof,
        ),
        BuiltinScene(
            "cornell-motion",
            "Cornell box with a moving box and a moving sphere (object motion blur by time slices)",
            _cornell_motion,
            object_motion={"moving-box": (0.45, 0.0, 0.0), "moving-sphere": (0.0, -0.35, 0.0)},
        ),
        BuiltinScene(
            "cornell-camera-motion",
            "Cornell box filmed by a camera that slides and turns during the shutter (exact per-ray camera motion)",
            lambda mi, w, h: {**_cornell_box(mi, w, h), "sensor": {**_cornell_box(mi, w, h)["sensor"], "shutter_open": 0.0, "shutter_close": 1.0}},
            camera_to_world_end=_camera_end(),
        ),
    )
}
