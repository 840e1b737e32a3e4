"""Indoor layouts: a box room, furniture, random objects and 1-5 lights, and the camera in it."""

from __future__ import annotations

from typing import Any

import numpy as np

from mcdenoise.render.procedural.camera import _Camera, _roll_up
from mcdenoise.render.procedural.materials import _material
from mcdenoise.render.procedural.objects import _add_object, _Builder, _random_object
from mcdenoise.render.procedural.seeds import _loguniform
from mcdenoise.render.procedural.transforms import _rotate, _scale, _translate, _xform, look_at

__all__ = []


#: Gap (metres) between the floor and the boxes standing on it, so that no two faces are coplanar
#: (ties between hits would be broken by BVH order; a precaution, not a measured problem).
LIFT = 1e-3


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
