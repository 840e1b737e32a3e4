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
are neither black nor blown out). Other camera views of a drawn scene:
:mod:`mcdenoise.render.procedural_views`.

What varies, per scene:

* kind: ``indoor`` (a box room, 1-5 pieces of furniture-like boxes, 1-5 area (ceiling disks,
  glowing spheres), point and spot lights)
  or ``outdoor`` (a flat or hilly ground, lit by a procedural HDR environment map or Mitsuba's
  ``sunsky``);
* 10-50 random objects: built-in ``sphere``/``cube``/``cylinder`` and procedural meshes
  (:mod:`mcdenoise.render.procedural_meshes`), with random scale, rotation and placement (outdoor:
  Poisson-disc positions within and slightly beyond the view; never too close to the camera);
* materials from :data:`MATERIALS` with textures from :data:`TEXTURES` and random UV scales, bump
  maps on some;
* camera: field of view, position, target, roll; thin-lens depth of field with probability 1/2;
  motion blur with probability 1/2 (linear motion of half the objects, and with probability 1/2
  also a camera motion).

Motion is not part of the Mitsuba dict (Mitsuba 3 has no moving shapes): it is in
:attr:`ProceduralScene.object_motion` (shape id -> translation over the shutter) and
:attr:`ProceduralScene.camera_to_world_end` for the renderer to apply.
"""

from __future__ import annotations

import gc
import hashlib
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mcdenoise.errors import SceneError
from mcdenoise.render import procedural_meshes as pm
from mcdenoise.render import procedural_textures as pt

__all__ = [
    "KINDS",
    "MATERIALS",
    "TEXTURES",
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

KINDS = ("indoor", "outdoor")
#: material plugin -> weight. Diffuse is favoured slightly, as in SBMC.
MATERIALS: dict[str, float] = {
    "diffuse": 0.2,
    "plastic": 0.1,
    "roughplastic": 0.15,
    "conductor": 0.07,
    "roughconductor": 0.13,
    "dielectric": 0.07,
    "roughdielectric": 0.08,
    "principled": 0.2,
}
#: texture kind -> weight, for colour parameters.
TEXTURES: dict[str, float] = {
    "constant": 0.35,
    "checkerboard": 0.15,
    "noise": 0.15,
    "stripes": 0.1,
    "cells": 0.1,
    "noise_stripes": 0.15,
}
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
CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr", "W", "Hg", "Ir", "Rh", "none")  # all ship with Mitsuba 3.9
MIN_OBJECTS, MAX_OBJECTS = 10, 50
MAX_ATTEMPTS = 12
#: Preview size (pixels on the long side) and samples per pixel of the standalone rejection check
#: (the dataset previews at the input image's own size and spp instead).
PREVIEW_SIZE, PREVIEW_SPP = 32, 8
#: Gap (metres) between the floor and the boxes standing on it, so that no two faces are coplanar
#: (ties between hits would be broken by BVH order; a precaution, not a measured problem).
LIFT = 1e-3


# --------------------------------------------------------------------------------------------
# Small helpers: seeds, matrices, random choices


def derive_seed(*ints: int) -> int:
    """A 31-bit seed derived from integers, e.g. ``(dataset_seed, image_index)`` (no clock)."""
    ss = np.random.SeedSequence([int(i) & 0xFFFFFFFFFFFFFFFF for i in ints])
    return int(ss.generate_state(1, np.uint32)[0] >> 1)


def _translate(t: Any) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def _scale(s: Any) -> np.ndarray:
    return np.diag([*np.broadcast_to(np.asarray(s, float), (3,)), 1.0])


def _rotate(axis: Any, angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)
    return m


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return m


def look_at(origin: Any, target: Any, up: Any) -> np.ndarray:
    """Camera-to-world 4x4 with Mitsuba's convention: local +Z forward, +Y up, +X to the left."""
    o = np.asarray(origin, float)
    d = np.asarray(target, float) - o
    d /= np.linalg.norm(d)
    left = np.cross(np.asarray(up, float), d)
    n = np.linalg.norm(left)
    if n < 1e-9:  # up parallel to the view direction: pick any perpendicular
        left = np.cross([1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 0.0, 1.0], d)
        n = np.linalg.norm(left)
    left /= n
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def _choice(rng: np.random.Generator, table: dict[str, float]) -> str:
    keys = list(table)
    p = np.array([table[k] for k in keys])
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _xform(m: np.ndarray) -> Any:
    return pm.mitsuba_module().ScalarTransform4f(np.asarray(m, np.float64).tolist())


def _bitmap(arr: np.ndarray) -> Any:
    return pm.mitsuba_module().Bitmap(np.ascontiguousarray(arr, np.float32))


# --------------------------------------------------------------------------------------------
# Textures and materials


def _texture(rng: np.random.Generator, used: dict[str, int], *, lo: float = 0.02, hi: float = 0.95) -> dict:
    """A colour texture plugin dict (constant, checkerboard or bitmap) with a random UV scale."""
    kind = _choice(rng, TEXTURES)
    used[kind] = used.get(kind, 0) + 1
    if kind == "constant":
        return {"type": "rgb", "value": rng.uniform(lo, hi, 3).tolist()}
    uv = _loguniform(rng, 0.5, 16.0)
    to_uv = _xform(_rotate([0, 0, 1], rng.uniform(0, 2 * np.pi)) @ _scale([uv, uv * rng.uniform(0.5, 2.0), 1.0]))
    if kind == "checkerboard":
        return {
            "type": "checkerboard",
            "color0": {"type": "rgb", "value": rng.uniform(lo, hi, 3).tolist()},
            "color1": {"type": "rgb", "value": rng.uniform(lo, hi, 3).tolist()},
            "to_uv": to_uv,
        }
    size = int(rng.choice([32, 64, 128]))
    img = lo + (hi - lo) * pt.texture_image(rng, kind, size)
    return {"type": "bitmap", "bitmap": _bitmap(img), "to_uv": to_uv, "raw": True, "filter_type": "bilinear"}


def _material(rng: np.random.Generator, used: dict[str, int], textures: dict[str, int], kind: str | None = None) -> dict:
    """A random BSDF plugin dict; ``used`` counts material kinds, ``textures`` texture kinds."""
    kind = kind or _choice(rng, MATERIALS)
    used[kind] = used.get(kind, 0) + 1
    alpha = _loguniform(rng, 0.02, 0.6)
    ior = float(rng.uniform(1.3, 1.9))
    if kind == "diffuse":
        bsdf: dict = {"type": "diffuse", "reflectance": _texture(rng, textures)}
    elif kind == "plastic":
        bsdf = {"type": "plastic", "diffuse_reflectance": _texture(rng, textures), "int_ior": ior}
    elif kind == "roughplastic":
        bsdf = {"type": "roughplastic", "diffuse_reflectance": _texture(rng, textures), "int_ior": ior, "alpha": alpha}
    elif kind == "conductor":
        bsdf = {"type": "conductor", "material": str(rng.choice(CONDUCTORS))}
        if bsdf["material"] == "none" or rng.random() < 0.3:
            bsdf["specular_reflectance"] = _texture(rng, textures, lo=0.3, hi=1.0)
    elif kind == "roughconductor":
        bsdf = {
            "type": "roughconductor",
            "material": str(rng.choice(CONDUCTORS)),
            "distribution": str(rng.choice(["ggx", "beckmann"])),
            "alpha": alpha,
        }
        if bsdf["material"] == "none" or rng.random() < 0.3:
            bsdf["specular_reflectance"] = _texture(rng, textures, lo=0.3, hi=1.0)
    elif kind == "dielectric":
        bsdf = {"type": "dielectric", "int_ior": ior}
        if rng.random() < 0.3:
            bsdf["specular_transmittance"] = {"type": "rgb", "value": rng.uniform(0.5, 1.0, 3).tolist()}
    elif kind == "roughdielectric":
        bsdf = {"type": "roughdielectric", "int_ior": ior, "alpha": alpha, "distribution": "ggx"}
    elif kind == "principled":
        bsdf = {
            "type": "principled",
            "base_color": _texture(rng, textures),
            "roughness": float(rng.uniform(0.05, 1.0)),
            "metallic": float(rng.choice([0.0, 0.0, 1.0, rng.uniform()])),
            "specular": float(rng.uniform(0.0, 1.0)),
            "spec_trans": float(rng.choice([0.0, 0.0, 0.0, rng.uniform()])),
            "clearcoat": float(rng.choice([0.0, rng.uniform()])),
            "clearcoat_gloss": float(rng.uniform()),
            "sheen": float(rng.choice([0.0, rng.uniform()])),
            "anisotropic": float(rng.choice([0.0, 0.0, rng.uniform()])),
        }
    else:
        raise ValueError(f"unknown material {kind!r}; materials: {sorted(MATERIALS)}")
    # Bump maps on some opaque materials (Mitsuba's bumpmap needs a raw scalar texture).
    if kind not in ("dielectric", "roughdielectric") and rng.random() < 0.2:
        size = 64
        h = pt.tileable_noise(rng, size, beta=rng.uniform(1.5, 3.0)) if rng.random() < 0.6 else pt.stripes(rng, size)
        uv = _loguniform(rng, 1.0, 16.0)
        textures["bump"] = textures.get("bump", 0) + 1
        bsdf = {
            "type": "bumpmap",
            "arg": {"type": "bitmap", "bitmap": _bitmap(h[..., None]), "raw": True, "to_uv": _xform(_scale([uv, uv, 1]))},
            "scale": float(rng.uniform(0.05, 0.5)),
            "nested": bsdf,
        }
    return bsdf


# --------------------------------------------------------------------------------------------
# Objects


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

    def add(self, key: str, value: Any) -> None:
        if key in self.scene:
            raise AssertionError(f"duplicate scene key {key}")
        self.scene[key] = value


def _add_object(b: _Builder, oid: str, shape: str, to_world: np.ndarray, bsdf: dict, radius: float) -> None:
    """Add a shape of kind ``shape`` whose unit-size version is mapped by ``to_world``."""
    b.shapes[shape] = b.shapes.get(shape, 0) + 1
    if shape in pm.MESH_BUILDERS:
        arrays = pm.MESH_BUILDERS[shape](b.rng)
        b.add(oid, pm.to_mitsuba_mesh(oid, arrays, bsdf=bsdf, to_world=to_world))
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


# --------------------------------------------------------------------------------------------
# Camera


@dataclass
class _Camera:
    origin: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov: float


def _sensor(b: _Builder, cam: _Camera, width: int, height: int, dof: bool) -> tuple[dict, float, float]:
    """Sensor dict; returns it with (aperture radius, focus distance)."""
    rng = b.rng
    to_world = look_at(cam.origin, cam.target, cam.up)
    d: dict = {
        "type": "perspective",
        "id": "camera",
        "fov": float(cam.fov),
        "fov_axis": "x",
        "to_world": _xform(to_world),
        "near_clip": 0.01,
        "far_clip": 10000.0,
        "film": {
            "type": "hdrfilm",
            "width": int(width),
            "height": int(height),
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
        "sampler": {"type": "independent", "sample_count": 4},
    }
    aperture, focus = 0.0, float(np.linalg.norm(cam.target - cam.origin))
    if dof:
        # Focus on the target or somewhere around it; aperture so that the circle of confusion of
        # objects at half/double the focus distance spans a few % of the image width.
        focus = focus * float(rng.uniform(0.6, 1.3))
        aperture = focus * math.tan(math.radians(cam.fov) / 2) * _loguniform(rng, 0.01, 0.08)
        d.update(type="thinlens", aperture_radius=float(aperture), focus_distance=float(focus))
    return d, aperture, focus


# --------------------------------------------------------------------------------------------
# Indoor


def _rect(center: Any, normal_rot: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """to_world of Mitsuba's rectangle ([-1, 1]^2 in XY, normal +Z) of half-sizes sx, sy."""
    return _translate(center) @ normal_rot @ _scale([sx, sy, 1.0])


def _indoor(b: _Builder, n_objects: int) -> _Camera:
    rng = b.rng
    w, dpt, h = rng.uniform(4, 10), rng.uniform(4, 10), rng.uniform(2.5, 4.0)
    hx, hz = w / 2, dpt / 2
    b.room = (float(hx), float(hz), float(h))
    wall_mat = _material(b.rng, b.materials, b.textures, kind=str(rng.choice(["diffuse", "roughplastic"])))
    floor_mat = _material(b.rng, b.materials, b.textures, kind=str(rng.choice(["diffuse", "roughplastic", "principled"])))
    ceil_mat = {"type": "diffuse", "reflectance": {"type": "rgb", "value": rng.uniform(0.5, 0.9, 3).tolist()}}
    # Rectangles face into the room.
    b.add("floor", {"type": "rectangle", "id": "floor", "to_world": _xform(_rect([0, 0, 0], _rotate([1, 0, 0], -np.pi / 2), hx, hz)), "bsdf": floor_mat})
    b.add("ceiling", {"type": "rectangle", "id": "ceiling", "to_world": _xform(_rect([0, h, 0], _rotate([1, 0, 0], np.pi / 2), hx, hz)), "bsdf": ceil_mat})
    walls = [
        ([0, h / 2, -hz], _rotate([0, 1, 0], 0.0), hx),
        ([0, h / 2, hz], _rotate([0, 1, 0], np.pi), hx),
        ([-hx, h / 2, 0], _rotate([0, 1, 0], np.pi / 2), hz),
        ([hx, h / 2, 0], _rotate([0, 1, 0], -np.pi / 2), hz),
    ]
    for i, (c, r, s) in enumerate(walls):
        b.add(f"wall_{i}", {"type": "rectangle", "id": f"wall_{i}", "to_world": _xform(_rect(c, r, s, h / 2)), "bsdf": wall_mat})

    # Camera first, so that furniture and objects can keep clear of it.
    cam_pos = np.array([rng.uniform(-hx + 0.4, hx - 0.4), rng.uniform(0.8, min(2.0, h - 0.3)), rng.uniform(-hz + 0.4, hz - 0.4)])
    # Look roughly across the room: towards a point on the far side of the centre.
    far = -np.sign(cam_pos[[0, 2]]) * np.array([hx, hz]) * rng.uniform(0.2, 0.9, 2)
    target = np.array([far[0], rng.uniform(0.3, 1.5), far[1]])
    cam = _Camera(cam_pos, target, _roll_up(rng), float(rng.uniform(40, 80)))

    def clear(p: np.ndarray, r: float) -> bool:
        return bool(np.linalg.norm(p - cam_pos) > r + 0.5)

    # Furniture: tables (top + 4 legs) and boxes (cabinets, beds, shelves) on the floor.
    tops: list[tuple[np.ndarray, float, float]] = []  # (centre of top surface, half x, half z)
    n_furn = int(rng.integers(1, 6))
    k = 0
    for f in range(n_furn):
        for _ in range(10):
            fx, fz = rng.uniform(-hx + 0.5, hx - 0.5), rng.uniform(-hz + 0.5, hz - 0.5)
            sx, sz = rng.uniform(0.3, 1.0), rng.uniform(0.3, 1.0)
            if clear(np.array([fx, 0.5, fz]), max(sx, sz)):
                break
        else:
            continue
        mat = _material(rng, b.materials, b.textures, kind=str(rng.choice(["diffuse", "roughplastic", "principled", "plastic"])))
        yaw = _rotate([0, 1, 0], rng.uniform(0, np.pi))
        if rng.random() < 0.5:  # table
            th = rng.uniform(0.5, 1.0)
            top = _translate([fx, th, fz]) @ yaw @ _scale([sx, 0.03, sz])
            _add_object(b, f"furniture_{k}", "cube", top, mat, max(sx, sz))
            k += 1
            for lx, lz in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
                leg_c = _translate([fx, LIFT, fz]) @ yaw @ _translate([lx * (sx - 0.05), th / 2, lz * (sz - 0.05)])
                _add_object(b, f"furniture_{k}", "cube", leg_c @ _scale([0.03, th / 2, 0.03]), mat, th / 2)
                k += 1
            tops.append((np.array([fx, th + 0.03, fz]), sx * 0.8, sz * 0.8))
        else:  # box: cabinet, bed, shelf
            bh = rng.uniform(0.3, min(2.0, h - 0.5))
            m = _translate([fx, bh / 2 + LIFT, fz]) @ yaw @ _scale([sx, bh / 2, sz])
            _add_object(b, f"furniture_{k}", "cube", m, mat, max(sx, sz, bh / 2))
            k += 1
            tops.append((np.array([fx, bh, fz]), sx * 0.7, sz * 0.7))

    # Random objects: on the floor, on furniture, or floating.
    # Furniture pieces count as objects, but at least a third of the count are random objects.
    for i in range(max(n_objects // 3, n_objects - len(b.objects))):
        size = _loguniform(rng, 0.08, 0.4)
        for _ in range(20):
            r = rng.random()
            if r < 0.35 and tops:
                c, ax, az = tops[int(rng.integers(len(tops)))]
                p = c + np.array([rng.uniform(-ax, ax), size, rng.uniform(-az, az)])
            elif r < 0.75:
                p = np.array([rng.uniform(-hx + size, hx - size), size, rng.uniform(-hz + size, hz - size)])
            else:
                p = np.array([rng.uniform(-hx + size, hx - size), rng.uniform(size, h - size), rng.uniform(-hz + size, hz - size)])
            if clear(p, size * 1.6):
                break
        _random_object(b, f"object_{i}", p, size)

    # Lights: 1-5 of area (ceiling panels, glowing spheres), point and spot.
    for j in range(int(rng.integers(1, 6))):
        col = rng.uniform(0.6, 1.0, 3)
        lid = f"light_{j}"
        kind = str(rng.choice(["area_panel", "area_sphere", "point", "spot"], p=[0.4, 0.15, 0.25, 0.2]))
        lp = np.array([rng.uniform(-hx + 0.5, hx - 0.5), rng.uniform(h * 0.6, h - 0.15), rng.uniform(-hz + 0.5, hz - 0.5)])
        if kind == "area_panel":
            # Round ceiling lamps: disks, not rectangles. Mitsuba 3.9 lists the emitters of
            # mesh shapes (rectangle, cube) in an order that changes from load to load, which
            # changes which light a random number picks: pixels would not be reproducible.
            r = rng.uniform(0.15, 0.6)
            m = _translate([lp[0], h - 0.01, lp[2]]) @ _rotate([1, 0, 0], np.pi / 2) @ _scale([r, r, 1.0])
            b.add(lid, {"type": "disk", "id": lid, "to_world": _xform(m), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": (col * 5.0).tolist()}}})
        elif kind == "area_sphere":
            r = rng.uniform(0.05, 0.2)
            b.add(lid, {"type": "sphere", "id": lid, "center": lp.tolist(), "radius": float(r), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": (col * 5.0 / (r * r)).tolist()}}})
        elif kind == "point":
            b.add(lid, {"type": "point", "id": lid, "position": lp.tolist(), "intensity": {"type": "rgb", "value": (col * 5.0).tolist()}})
        else:
            tgt = np.array([rng.uniform(-hx, hx), 0.0, rng.uniform(-hz, hz)])
            b.add(lid, {
                "type": "spot", "id": lid, "to_world": _xform(look_at(lp, tgt, [0.3, 0.2, 1.0])),
                "cutoff_angle": float(rng.uniform(15, 60)), "intensity": {"type": "rgb", "value": (col * 15.0).tolist()},
            })
        b.emitters.append(lid)
    return cam


def _roll_up(rng: np.random.Generator) -> np.ndarray:
    """An up vector near +Y: most cameras are level, some tilted (SBMC randomises the up vector)."""
    roll = rng.normal(0, 0.08) if rng.random() < 0.7 else rng.uniform(-0.6, 0.6)
    return np.array([math.sin(roll), math.cos(roll), 0.0])


# --------------------------------------------------------------------------------------------
# Outdoor


def _poisson_disc(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, radius: float, limit: int) -> np.ndarray:
    """Dart-throwing Poisson-disc samples in the 2D box [lo, hi] (at most ``limit`` points)."""
    pts = np.empty((limit, 2))
    n = 0
    for p in rng.uniform(lo, hi, size=(limit * 30, 2)):
        if n == 0 or ((pts[:n] - p) ** 2).sum(axis=1).min() >= radius * radius:
            pts[n] = p
            n += 1
            if n >= limit:
                break
    return pts[:n]


def _outdoor(b: _Builder, n_objects: int) -> _Camera:
    rng = b.rng
    ground_mat = _material(rng, b.materials, b.textures, kind=str(rng.choice(["diffuse", "roughplastic", "principled"])))
    if rng.random() < 0.5:
        b.add("ground", {"type": "rectangle", "id": "ground", "to_world": _xform(_rotate([1, 0, 0], -np.pi / 2) @ _scale([200, 200, 1])), "bsdf": ground_mat})
    else:
        arrays = pm.terrain(rng, size=120.0, height=rng.uniform(2.0, 15.0))
        b.add("ground", pm.to_mitsuba_mesh("ground", arrays, bsdf=ground_mat))

    if rng.random() < 0.4:
        elev = rng.uniform(0.05, 1.3)
        az = rng.uniform(0, 2 * np.pi)
        b.add("sky", {
            "type": "sunsky", "id": "sky",
            "sun_direction": [math.cos(elev) * math.sin(az), math.sin(elev), -math.cos(elev) * math.cos(az)],
            "turbidity": float(rng.uniform(2.0, 8.0)), "sun_scale": 1.0, "sky_scale": 1.0,
            # Mitsuba's sunsky is Z-up; our world is Y-up. sun_direction is in world space
            # (checked: with this rotation a sun at +Y lights the sky above, none below).
            "to_world": _xform(_rotate([1, 0, 0], -np.pi / 2)),
        })
        b.textures["sunsky"] = 1
    else:
        style, img = pt.envmap_image(rng, 64, 128)
        b.textures[f"envmap_{style}"] = 1
        b.add("sky", {"type": "envmap", "id": "sky", "bitmap": _bitmap(img), "scale": 1.0,
                      "to_world": _xform(_rotate([0, 1, 0], rng.uniform(0, 2 * np.pi)))})
    b.emitters.append("sky")

    fov = float(rng.uniform(30, 70))
    cam_h = rng.uniform(0.5, 3.0)
    heading = rng.uniform(0, 2 * np.pi)
    fwd = np.array([math.sin(heading), 0.0, math.cos(heading)])
    side = np.array([fwd[2], 0.0, -fwd[0]])
    scale = _loguniform(rng, 0.3, 1.5)  # object size scale for this scene
    dist = rng.uniform(3.0, 10.0) * scale
    origin = np.array([0.0, cam_h, 0.0])
    # Poisson-disc candidate positions on the ground within and slightly beyond the frustum.
    half = math.tan(math.radians(fov) / 2) * 1.2
    depth_lo, depth_hi = 1.5 * scale, dist * 2.5
    pts = _poisson_disc(rng, np.array([depth_lo, -1.0]), np.array([depth_hi, 1.0]), rng.uniform(0.05, 0.15), MAX_OBJECTS * 3)
    cand = [origin * [1, 0, 1] + fwd * u + side * (v * half * u) for u, v in pts]
    rng.shuffle(cand)
    target = origin * [1, 0, 1] + fwd * dist + np.array([0.0, rng.uniform(0.0, 1.0) * scale, 0.0])
    cam = _Camera(origin, target, _roll_up(rng), fov)
    for i in range(min(n_objects, len(cand))):
        p = np.array(cand[i], float)
        # No object closer than 5 radii: one object filling the view makes a useless image.
        size = min(_loguniform(rng, 0.2, 1.0) * scale, float(np.linalg.norm(p - origin)) / 5)
        p[1] = size if rng.random() < 0.7 else size + rng.uniform(0, 2.0) * scale  # some float
        _random_object(b, f"object_{i}", p, size)
    return cam


# --------------------------------------------------------------------------------------------
# Public API


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


def _draw(
    seed: int, kind: str | None, width: int, height: int, objects: tuple[int, int] = (MIN_OBJECTS, MAX_OBJECTS)
) -> ProceduralScene:
    """Draw one scene from ``seed`` without any check."""
    rng = np.random.default_rng(seed)
    kind = kind or str(rng.choice(KINDS))
    if kind not in KINDS:
        raise SceneError(f"unknown procedural scene kind {kind!r}; kinds: {', '.join(KINDS)}")
    lo, hi = objects
    if not 1 <= lo <= hi <= 1000:
        raise SceneError(f"procedural scene: object count range {lo}-{hi} must satisfy 1 <= min <= max <= 1000")
    b = _Builder(rng)
    n_objects = int(rng.integers(lo, hi + 1))
    dof = bool(rng.random() < 0.5)
    motion = bool(rng.random() < 0.5)
    cam = (_indoor if kind == "indoor" else _outdoor)(b, n_objects)
    sensor, aperture, focus = _sensor(b, cam, width, height, dof)
    cam_close = None
    obj_motion: dict[str, list[float]] = {}
    shutter = (0.0, 0.0)
    if motion:
        shutter = (0.0, float(rng.uniform(0.5, 1.0)))
        sensor["shutter_open"], sensor["shutter_close"] = shutter
        # Linear motion of about half the random objects (not furniture), as in SBMC.
        scale = float(np.median([r for _, r in b.extents.values()])) if b.extents else 0.3
        for oid in b.objects:
            if oid.startswith("object_") and rng.random() < 0.5:
                v = rng.normal(size=3)
                obj_motion[oid] = (v / np.linalg.norm(v) * scale * rng.uniform(0.1, 1.0)).tolist()
        if rng.random() < 0.5:
            dist = float(np.linalg.norm(cam.target - cam.origin))
            shift = rng.normal(size=3) * dist * 0.02
            turn = _rotate([0, 1, 0], rng.normal(0, 0.02))
            c2w = look_at(cam.origin, cam.target, cam.up)
            cam_close = _translate(shift) @ c2w @ turn
    b.add("sensor", sensor)
    info = {
        "kind": kind,
        "objects": sum(1 for o in b.objects if o.startswith("object_")),
        "furniture": sum(1 for o in b.objects if o.startswith("furniture_")),
        "lights": len(b.emitters),
        "materials": dict(sorted(b.materials.items())),
        "textures": dict(sorted(b.textures.items())),
        "shapes": dict(sorted(b.shapes.items())),
        "depth_of_field": dof,
        "motion_blur": motion,
        "moving_objects": len(obj_motion),
        "camera_motion": cam_close is not None,
    }
    return ProceduralScene(
        scene=b.scene,
        seed=seed,
        drawn_seed=seed,
        attempts=0,
        kind=kind,
        camera_to_world=look_at(cam.origin, cam.target, cam.up),
        fov=cam.fov,
        aperture_radius=aperture,
        focus_distance=focus,
        depth_of_field=dof,
        motion_blur=motion,
        shutter=shutter,
        camera_to_world_end=cam_close,
        object_motion=obj_motion,
        camera_path=(cam.origin.copy(), cam.target.copy(), cam.up.copy()),
        info=info,
        extents={k: (c.copy(), float(r)) for k, (c, r) in b.extents.items()},
        room=b.room,
    )


@dataclass
class PreviewStats:
    """What the rejection check measured on a tiny render (luminances are linear)."""

    mean: float
    median: float
    black_fraction: float
    object_fraction: float
    finite: bool

    def problem(self) -> str | None:
        """Why the scene is rejected, or None when it is fine."""
        if not self.finite:
            return "non-finite pixels"
        if self.mean <= 1e-8 or self.median <= 1e-12:
            return "renders black"
        if self.black_fraction > 0.5:
            return f"{self.black_fraction:.0%} of the image is black"
        if self.object_fraction < 0.08:
            return f"objects cover only {self.object_fraction:.0%} of the image"
        return None


def preview_stats(
    ps: ProceduralScene,
    *,
    size: int = PREVIEW_SIZE,
    spp: int = PREVIEW_SPP,
    seed: int = 0,
    scene: Any = None,
    settings: Any = None,
    record_position: bool = False,
) -> PreviewStats:
    """Render ``ps`` cheaply with our integrator and measure luminance statistics, plus object
    coverage from one ray per pixel centre.

    Standalone (``scene``/``settings`` None): the dict is loaded with its film shrunk to ``size``
    pixels on the long side and rendered at ``spp``. The dataset instead passes its loaded
    ``scene`` and the input image's own :class:`~mcdenoise.render.api.RenderSettings` (size, spp,
    motion), so that the preview compiles exactly the kernel the input then reuses: the check
    costs one input-sized trace, not a compilation of its own. ``seed`` replaces the settings'
    seed (the preview's noise is independent of the input's).
    """
    from dataclasses import replace

    from mcdenoise.render.api import RenderSettings, render_samples

    mi = pm.mitsuba_module()
    if settings is None:
        film = ps.scene["sensor"]["film"]
        w, h = film["width"], film["height"]
        k = size / max(w, h)
        settings = RenderSettings(spp=spp, ref_spp=0, width=max(1, round(w * k)), height=max(1, round(h * k)), max_depth=6)
    settings = replace(settings, seed=int(seed))
    if scene is None:
        scene = load_procedural(ps, settings.width, settings.height)
    arrays, _ = render_samples(scene, settings, record_position=record_position)
    img = arrays["radiance"].mean(axis=0, dtype=np.float64).transpose(1, 2, 0)
    del arrays
    lum = img @ np.array([0.2126, 0.7152, 0.0722])
    is_obj = _object_mask(mi, scene, settings.width, settings.height)
    finite = bool(np.isfinite(img).all())
    mean = float(lum.mean()) if finite else 0.0
    return PreviewStats(
        mean=mean,
        median=float(np.median(lum)) if finite else 0.0,
        black_fraction=float((lum <= 1e-4 * max(mean, 1e-30)).mean()),
        object_fraction=float(is_obj.mean()),
        finite=finite,
    )


def load_procedural(ps: ProceduralScene, width: int, height: int) -> Any:
    """Load ``ps.scene`` at ``width`` x ``height``; SceneError naming the seed when it fails."""
    from mcdenoise.render.api import load_scene

    try:
        return load_scene(ps.scene, width=width, height=height)
    except SceneError as e:
        raise SceneError(f"procedural scene (seed {ps.drawn_seed}) does not load: {e}") from None


def _object_mask(mi: Any, loaded: Any, width: int, height: int) -> np.ndarray:
    """(height, width) bool: the ray through the pixel centre first hits a random object or
    furniture (shapes compared by their Dr.Jit registry ids, one vectorised ray cast).

    A preliminary intersection is enough to know the shape, and its kernel is tiny (a full
    ``ray_intersect`` evaluates textures and frames of every material).
    """
    import drjit as dr

    sensor = loaded.sensors()[0]
    y, x = np.mgrid[0:height, 0:width]
    film_pos = mi.Point2f(((x.ravel() + 0.5) / width).astype(np.float32), ((y.ravel() + 0.5) / height).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, film_pos, mi.Point2f(0.5, 0.5))
    hit_ids = np.array(dr.reinterpret_array(mi.UInt32, loaded.ray_intersect_preliminary(ray).shape))
    obj_ids = [
        int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s)))[0])
        for s in loaded.shapes()
        if s.id().startswith(("object_", "furniture_"))
    ]
    return np.isin(hit_ids, obj_ids).reshape(height, width)


def _scale_emitters(node: Any, k: float) -> None:
    """Multiply the strength of every emitter plugin dict under ``node`` by ``k`` (in place)."""
    if not isinstance(node, dict):
        return
    t = node.get("type")
    if t == "area":
        node["radiance"]["value"] = [v * k for v in node["radiance"]["value"]]
    elif t in ("point", "spot"):
        node["intensity"]["value"] = [v * k for v in node["intensity"]["value"]]
    elif t == "envmap":
        node["scale"] = node.get("scale", 1.0) * k
    elif t == "sunsky":
        node["sun_scale"] = node.get("sun_scale", 1.0) * k
        node["sky_scale"] = node.get("sky_scale", 1.0) * k
    for v in node.values():
        _scale_emitters(v, k)


def generate(
    seed: int,
    *,
    kind: str | None = None,
    width: int = 128,
    height: int = 128,
    check: bool = True,
    max_attempts: int = MAX_ATTEMPTS,
    objects: tuple[int, int] = (MIN_OBJECTS, MAX_OBJECTS),
    settings: Any = None,
    record_position: bool = False,
    keep_loaded: bool = False,
) -> ProceduralScene:
    """Draw a scene from ``seed``; with ``check``, re-draw rejected ones from derived seeds.

    ``width``/``height`` set the film in the dict. ``objects`` is the (min, max) number of
    objects: indoor scenes count their furniture pieces in it when there is room. JIT compilation
    time grows with it: every object's material is compiled into the kernel separately. Raises
    SceneError when ``max_attempts`` drawings in a row are rejected.

    With ``keep_loaded`` the scene is loaded once at ``width`` x ``height`` (camera made opaque,
    :func:`~mcdenoise.render.procedural_views.set_camera`), checked on that very object with the
    render ``settings`` the caller will use (a RenderSettings, or a function of the drawn scene
    returning one, e.g. to include its motion) and ``record_position``, so the preview compiles
    the caller's kernel, and returned in :attr:`ProceduralScene.loaded` with its emitters
    rescaled in place. Without it the preview is a small standalone render (``PREVIEW_SIZE``).
    """
    from mcdenoise.render import procedural_views as pv

    reasons: list[str] = []
    for attempt in range(max_attempts):
        drawn = seed if attempt == 0 else derive_seed(seed, attempt)
        ps = _draw(drawn, kind, width, height, objects)
        ps.seed, ps.drawn_seed, ps.attempts = seed, drawn, attempt
        if keep_loaded:
            ps.loaded = load_procedural(ps, width, height)
            pv.set_camera(ps.loaded, ps.camera_to_world)
            # Emitter strengths opaque before the preview compiles (an envmap's scale loads as
            # a literal), so that the exposure fix below leaves the kernel as it is.
            pv.scale_loaded_emitters(ps.loaded, ps.scene)
        if not check:
            return ps
        pset = (settings(ps) if callable(settings) else settings) if keep_loaded else None
        stats = preview_stats(ps, scene=ps.loaded, settings=pset,
                              seed=derive_seed(drawn, 8) if keep_loaded else 0, record_position=record_position)
        problem = stats.problem()
        if problem is None:
            # Exposure: bring the median luminance into [0.05, 0.5] (random in log space); the
            # median ignores the sun and lamps seen directly, which dominate the mean.
            target = _loguniform(np.random.default_rng(derive_seed(drawn, 7)), 0.05, 0.5)
            k = target / stats.median
            _scale_emitters(ps.scene, k)
            if ps.loaded is not None:
                pv.scale_loaded_emitters(ps.loaded, ps.scene, k)
            ps.info.update(
                preview={"mean": stats.mean * k, "median": target, "black_fraction": stats.black_fraction,
                         "object_fraction": stats.object_fraction},
                emitter_scale=k,
                rejected=reasons,
            )
            return ps
        reasons.append(f"seed {drawn}: {problem}")
        # Free the rejected scene now: Dr.Jit compiles calls to every live BSDF of the process.
        del ps
        gc.collect()
    raise SceneError(f"procedural scene seed {seed}: {max_attempts} drawings rejected ({'; '.join(reasons[-3:])})")


def generate_scene(seed: int, *, kind: str | None = None, objects: tuple[int, int] = (MIN_OBJECTS, MAX_OBJECTS)) -> dict:
    """Mitsuba scene dict of the checked scene drawn from ``seed`` (see :func:`generate`)."""
    return generate(seed, kind=kind, objects=objects).scene


def scene_digest(node: Any) -> str:
    """A hex digest of a scene dict that sees through Mitsuba objects (meshes, bitmaps,
    transforms), so two dicts drawn from the same seed can be compared."""
    h = hashlib.sha256()
    _digest(node, h)
    return h.hexdigest()


def _digest(node: Any, h: Any) -> None:
    mi = pm.mitsuba_module()
    if isinstance(node, dict):
        h.update(b"{")
        for k in sorted(node):
            h.update(str(k).encode())
            _digest(node[k], h)
        h.update(b"}")
    elif isinstance(node, (list, tuple)):
        h.update(b"[")
        for v in node:
            _digest(v, h)
        h.update(b"]")
    elif isinstance(node, np.ndarray):
        h.update(np.ascontiguousarray(node).tobytes())
    elif isinstance(node, mi.Bitmap):
        h.update(np.ascontiguousarray(np.array(node)).tobytes())
    elif isinstance(node, mi.Mesh):
        params = mi.traverse(node)
        for key in ("vertex_positions", "faces", "vertex_texcoords"):
            h.update(np.array(params[key]).tobytes())
        h.update(str(node.bsdf()).encode())
    elif isinstance(node, mi.ScalarTransform4f):
        h.update(np.array(node.matrix, np.float64).tobytes())
    else:
        h.update(repr(node).encode())
