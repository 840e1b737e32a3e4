"""Scene-building state and the random objects placed in a scene.

:class:`_Builder` collects the Mitsuba dict and counts of what was drawn while one scene is drawn;
objects are built-in shapes or procedural meshes (:mod:`mcdenoise.render.procedural.meshes`) with a
random material.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from mcdenoise.render.procedural import meshes as pm
from mcdenoise.render.procedural.materials import _material
from mcdenoise.render.procedural.seeds import _choice
from mcdenoise.render.procedural.transforms import _random_rotation, _scale, _translate, _xform

__all__ = ["SHAPES", "MIN_OBJECTS", "MAX_OBJECTS"]


SHAPES: dict[str, float] = {
    "sphere": 0.15,
    "cube": 0.15,
    "cylinder": 0.05,
    "displaced_sphere": 0.2,
    "torus": 0.12,
    "extrusion": 0.13,
    "superquadric": 0.12,
    "twisted_column": 0.08,
}
MIN_OBJECTS, MAX_OBJECTS = 10, 50


@dataclass
class _Builder:
    """Mutable state while one scene is drawn."""

    rng: np.random.Generator
    scene: dict = field(default_factory=lambda: {"type": "scene"})
    materials: dict[str, int] = field(default_factory=dict)
    textures: dict[str, int] = field(default_factory=dict)
    shapes: dict[str, int] = field(default_factory=dict)
    objects: list[str] = field(default_factory=list)  # ids of random objects and furniture
    emitters: list[str] = field(default_factory=list)
    extents: dict[str, tuple[np.ndarray, float]] = field(default_factory=dict)  # id -> centre, radius
    room: tuple[float, float, float] | None = None  # indoor: half width (x), half depth (z), height
    #: called on a procedural mesh's BSDF dict before the mesh loads it (the detailed world's pass)
    detail: Callable[[dict], None] | None = None

    def add(self, key: str, value: Any) -> None:
        if key in self.scene:
            raise AssertionError(f"duplicate scene key {key}")
        self.scene[key] = value


def _mesh(b: _Builder, name: str, arrays: pm.MeshArrays, bsdf: dict, to_world: np.ndarray | None = None) -> Any:
    """A procedural mesh with ``bsdf``, after the builder's detail pass (if any) has seen it."""
    if b.detail is not None:
        b.detail(bsdf)
    return pm.to_mitsuba_mesh(name, arrays, bsdf=bsdf, to_world=to_world)


def _add_object(b: _Builder, oid: str, shape: str, to_world: np.ndarray, bsdf: dict, radius: float) -> None:
    """Add a shape of kind ``shape`` whose unit-size version is mapped by ``to_world``."""
    b.shapes[shape] = b.shapes.get(shape, 0) + 1
    if shape in pm.MESH_BUILDERS:
        arrays = pm.MESH_BUILDERS[shape](b.rng)
        b.add(oid, _mesh(b, oid, arrays, bsdf, to_world))
    else:
        # Built-ins have unit size already: sphere radius 1, cube [-1, 1]^3, cylinder r=1 along z.
        d: dict = {"type": shape, "id": oid, "to_world": _xform(to_world), "bsdf": bsdf}
        if shape == "cylinder":
            d["to_world"] = _xform(to_world @ _translate([0, 0, -1]) @ _scale([1, 1, 2]))
        b.add(oid, d)
    b.objects.append(oid)
    b.extents[oid] = (to_world[:3, 3].copy(), radius)


def _random_object(b: _Builder, oid: str, centre: np.ndarray, size: float) -> None:
    rng = b.rng
    shape = _choice(rng, SHAPES)
    # Built-in spheres and cylinders only take uniform scales (cylinders: along their axis too).
    aniso = np.ones(3)
    if rng.random() < 0.5:
        if shape == "cube":
            aniso = rng.uniform(0.6, 1.4, 3)
        elif shape == "cylinder":
            aniso = np.array([1.0, 1.0, rng.uniform(0.5, 2.0)])
    m = _translate(centre) @ _random_rotation(rng) @ _scale(size * aniso)
    _add_object(b, oid, shape, m, _material(rng, b.materials, b.textures), size * float(aniso.max()) * 1.6)
