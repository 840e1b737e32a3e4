"""A random Cycles scene description, drawn from (seed, index) with numpy alone (no ``bpy``).

The description is plain JSON (lists, numbers, strings): :mod:`mcdenoise.render.cycles.build`
turns it into a Blender scene. Drawing apart from building keeps the randomness testable without
Blender and makes a dataset's scenes the same on any machine: the draw uses only numpy's PCG64.

What it draws, after issue 19's list of what real scenes have (never after any particular scene):

* three kinds of setting: a **room** (a box, often with a window in one wall that lets in a sun
  and a sky, so that most of the room is lit indirectly; lamps inside), **outdoor** (a large
  textured ground under a sun and a sky, or a plain sky) and **studio** (a floor in a dark world,
  lit by a few small and very bright lights);
* small and very bright emitters seen directly and in glossy surfaces: point lights of 2 mm-5 cm
  at up to 2 kW, small emissive objects;
* materials: diffuse, glossy plastic, rough and polished metal, clear and frosted glass, fine
  procedural textures (checker, noise, Voronoi, waves, bricks, magic) at scales up to 80 per unit;
* brightness that varies by orders of magnitude between scenes (a per-scene exposure of the
  lights), depth of field in a third of the views.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["KINDS", "SHAPES", "MATERIALS", "TEXTURES", "draw_scene", "scene_rng"]

#: Setting -> weight.
KINDS = {"room": 0.45, "outdoor": 0.3, "studio": 0.25}
#: Primitive mesh -> weight (``bpy.ops.mesh.primitive_<name>_add``).
SHAPES = {"uv_sphere": 0.25, "cube": 0.2, "cylinder": 0.15, "torus": 0.1, "cone": 0.1, "ico_sphere": 0.1, "monkey": 0.1}
#: Material kind -> weight.
MATERIALS = {"diffuse": 0.2, "textured": 0.2, "plastic": 0.15, "metal": 0.15, "mirror": 0.05, "glass": 0.12,
             "textured_glossy": 0.08, "emissive": 0.05}
#: Procedural texture node -> weight.
TEXTURES = {"checker": 0.2, "noise": 0.2, "voronoi": 0.15, "wave": 0.15, "brick": 0.15, "magic": 0.15}
#: Conductor colours (base colour of a metallic Principled BSDF): silver, gold, copper, aluminium, iron.
METALS = ((0.97, 0.96, 0.91), (1.0, 0.77, 0.34), (0.96, 0.64, 0.54), (0.91, 0.92, 0.92), (0.53, 0.51, 0.5))


def scene_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of scene ``index`` of dataset ``seed``: independent of every other scene."""
    return np.random.default_rng([seed, index, 0x43594331])  # "CYC1": apart from the Mitsuba draws


def _pick(rng: np.random.Generator, table: dict[str, float]) -> str:
    names = list(table)
    p = np.array([table[n] for n in names], float)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def _colour(rng: np.random.Generator, lo: float = 0.03, hi: float = 0.9) -> list[float]:
    """A reflectance colour: a hue, saturation and value drawn apart (greys are common)."""
    v = float(rng.uniform(lo, hi))
    s = float(rng.choice([0.0, rng.uniform(0, 0.9)], p=[0.3, 0.7]))
    base = rng.uniform(0, 1, 3)
    c = v * ((1 - s) + s * base / max(base.max(), 1e-6))
    return [round(float(x), 4) for x in c]


def _texture(rng: np.random.Generator) -> dict[str, Any]:
    return {"type": _pick(rng, TEXTURES), "scale": float(np.exp(rng.uniform(math.log(2), math.log(80)))),
            "detail": float(rng.uniform(0, 8)), "a": _colour(rng), "b": _colour(rng)}


def draw_material(rng: np.random.Generator, kind: str | None = None, *, exposure: float = 1.0) -> dict[str, Any]:
    """One material: ``{"kind", "colour", "roughness", ...}`` (see :mod:`build` for each kind)."""
    kind = kind or _pick(rng, MATERIALS)
    m: dict[str, Any] = {"kind": kind, "colour": _colour(rng), "roughness": float(rng.uniform(0.3, 1.0))}
    if kind in ("plastic", "textured_glossy"):
        m["roughness"] = float(rng.uniform(0.02, 0.4))
    elif kind == "metal":
        m["colour"] = list(METALS[int(rng.integers(len(METALS)))])
        m["roughness"] = float(rng.uniform(0.03, 0.45))
    elif kind == "mirror":
        m["colour"] = list(METALS[int(rng.integers(len(METALS)))])
        m["roughness"] = 0.0
    elif kind == "glass":
        m["colour"] = [round(float(x), 4) for x in 1 - rng.uniform(0, 0.25, 3) * rng.integers(0, 2)]
        m["roughness"] = float(rng.choice([0.0, rng.uniform(0.02, 0.2)], p=[0.7, 0.3]))
        m["ior"] = float(rng.uniform(1.33, 1.7))
    elif kind == "emissive":
        m["strength"] = float(np.exp(rng.uniform(math.log(5), math.log(2000)))) * exposure
    if kind.startswith("textured"):
        m["texture"] = _texture(rng)
    return m


def _objects(rng: np.random.Generator, n: int, centre: tuple[float, float], spread: float, *,
             exposure: float, glass_bias: float = 0.0) -> list[dict[str, Any]]:
    out = []
    for _ in range(n):
        size = float(np.exp(rng.uniform(math.log(0.12), math.log(0.8))))
        x = centre[0] + float(rng.uniform(-spread, spread))
        y = centre[1] + float(rng.uniform(-spread, spread))
        lift = float(rng.choice([0.0, rng.uniform(0.1, 1.2)], p=[0.75, 0.25]))
        mat = draw_material(rng, "glass" if rng.uniform() < glass_bias else None, exposure=exposure)
        if mat["kind"] == "emissive":
            size = min(size, 0.15)  # a small bright thing, not a second sun
        out.append({"shape": _pick(rng, SHAPES), "size": size, "location": [x, y, size / 2 + lift],
                    "rotation": [float(a) for a in rng.uniform(0, 2 * math.pi, 3)], "material": mat})
    return out


def _point_light(rng: np.random.Generator, where: list[float], exposure: float) -> dict[str, Any]:
    return {"type": "POINT", "location": where, "radius": float(np.exp(rng.uniform(math.log(0.002), math.log(0.05)))),
            "energy": float(np.exp(rng.uniform(math.log(5), math.log(2000)))) * exposure, "visible": True}


def _sky(rng: np.random.Generator, exposure: float) -> dict[str, Any]:
    """A sun and a sky (Nishita), or a plain sky colour without a sun."""
    if rng.uniform() < 0.75:
        elevation = float(rng.uniform(5, 70))
        return {"type": "sun", "elevation": elevation, "rotation": float(rng.uniform(0, 360)),
                "sun_strength": float(rng.uniform(1, 8)) * exposure, "sun_angle": float(rng.uniform(0.5, 4)),
                "sky_strength": float(rng.uniform(0.1, 1.0)) * exposure}
    return {"type": "plain", "colour": _colour(rng, 0.3, 1.0), "strength": float(rng.uniform(0.2, 3)) * exposure}


def _camera(rng: np.random.Generator, location: list[float], target: list[float],
            objects: list[dict[str, Any]]) -> dict[str, Any]:
    cam: dict[str, Any] = {"location": location, "target": target,
                           "lens": float(np.exp(rng.uniform(math.log(18), math.log(85))))}
    if objects and rng.uniform() < 0.33:
        focus = objects[int(rng.integers(len(objects)))]["location"]
        cam["dof"] = {"fstop": float(np.exp(rng.uniform(math.log(0.7), math.log(5.6)))),
                      "distance": max(0.2, math.dist(location, focus))}
    return cam


def _room(rng: np.random.Generator, exposure: float) -> dict[str, Any]:
    w, d, h = float(rng.uniform(3, 8)), float(rng.uniform(3, 8)), float(rng.uniform(2.4, 4))
    floor = draw_material(rng, "textured" if rng.uniform() < 0.6 else "diffuse")
    walls = draw_material(rng, "textured" if rng.uniform() < 0.3 else "diffuse")
    ceiling = draw_material(rng, "diffuse")
    window = None
    if rng.uniform() < 0.65:
        ww, wh = float(rng.uniform(0.6, min(3.0, w - 0.6))), float(rng.uniform(0.6, h - 0.8))
        window = {"wall": str(rng.choice(["back", "left", "right"])), "width": ww, "height": wh,
                  "offset": float(rng.uniform(-(w - ww) / 2 + 0.2, (w - ww) / 2 - 0.2)),
                  "sill": float(rng.uniform(0.3, h - wh - 0.1))}
    lights: list[dict[str, Any]] = []
    n_lamps = int(rng.integers(0 if window else 1, 4))
    for _ in range(n_lamps):
        where = [float(rng.uniform(-w / 2 + 0.3, w / 2 - 0.3)), float(rng.uniform(-d / 2 + 0.3, d / 2 - 0.3)),
                 float(rng.uniform(0.5, h - 0.1))]
        if rng.uniform() < 0.5:
            lights.append(_point_light(rng, where, exposure))
        else:
            where[2] = h - 0.02
            lights.append({"type": "AREA", "location": where, "size": float(rng.uniform(0.2, 1.5)),
                           "energy": float(np.exp(rng.uniform(math.log(20), math.log(800)))) * exposure,
                           "visible": bool(rng.uniform() < 0.7)})
    objects = _objects(rng, int(rng.integers(3, 10)), (0.0, 0.0), min(w, d) / 2 - 0.6, exposure=exposure)
    world = _sky(rng, exposure * 3) if window else {"type": "plain", "colour": [0, 0, 0], "strength": 0.0}
    eye = [float(rng.uniform(-w / 2 + 0.4, w / 2 - 0.4)), -d / 2 + float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.8, h - 0.5))]
    target = [float(rng.uniform(-w / 3, w / 3)), float(rng.uniform(0, d / 2)), float(rng.uniform(0.3, h * 0.7))]
    return {"kind": "room", "room": {"width": w, "depth": d, "height": h, "floor": floor, "walls": walls,
                                     "ceiling": ceiling, "window": window},
            "objects": objects, "lights": lights, "world": world, "camera": _camera(rng, eye, target, objects)}


def _open(rng: np.random.Generator, kind: str, exposure: float) -> dict[str, Any]:
    objects = _objects(rng, int(rng.integers(3, 10)), (0.0, 0.0), float(rng.uniform(0.8, 2.5)), exposure=exposure,
                       glass_bias=0.25 if kind == "studio" else 0.0)
    floor = draw_material(rng, "textured" if rng.uniform() < 0.7 else draw_material(rng)["kind"])
    if floor["kind"] == "emissive":
        floor = draw_material(rng, "diffuse")
    lights: list[dict[str, Any]] = []
    if kind == "outdoor":
        world = _sky(rng, exposure)
        if rng.uniform() < 0.25:
            lights.append(_point_light(rng, [float(rng.uniform(-2, 2)), float(rng.uniform(-2, 2)),
                                             float(rng.uniform(0.3, 2))], exposure))
    else:
        world = {"type": "plain", "colour": _colour(rng, 0.2, 1.0), "strength": float(rng.uniform(0, 0.08)) * exposure}
        for _ in range(int(rng.integers(1, 4))):
            where = [float(rng.uniform(-3, 3)), float(rng.uniform(-3, 3)), float(rng.uniform(0.2, 3))]
            if rng.uniform() < 0.6:
                lights.append(_point_light(rng, where, exposure))
            else:
                lights.append({"type": "SPOT", "location": where, "target": [0.0, 0.0, 0.0],
                               "radius": float(rng.uniform(0.005, 0.1)), "spot_size": float(rng.uniform(20, 90)),
                               "energy": float(np.exp(rng.uniform(math.log(50), math.log(3000)))) * exposure,
                               "visible": True})
    dist = float(rng.uniform(2.0, 6.0))
    azimuth, elevation = float(rng.uniform(0, 2 * math.pi)), math.radians(float(rng.uniform(4, 45)))
    eye = [dist * math.cos(elevation) * math.cos(azimuth), dist * math.cos(elevation) * math.sin(azimuth),
           0.15 + dist * math.sin(elevation)]
    target = [float(rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.5, 0.5)), float(rng.uniform(0, 0.6))]
    return {"kind": kind, "floor": floor, "objects": objects, "lights": lights, "world": world,
            "camera": _camera(rng, eye, target, objects)}


def draw_scene(seed: int, index: int) -> dict[str, Any]:
    """The description of scene ``index`` of dataset ``seed`` (JSON-able)."""
    rng = scene_rng(seed, index)
    kind = _pick(rng, KINDS)
    exposure = float(np.exp(rng.uniform(math.log(0.1), math.log(10))))  # brightness over two decades
    scene = _room(rng, exposure) if kind == "room" else _open(rng, kind, exposure)
    scene.update(seed=seed, index=index, exposure=exposure)
    return scene
