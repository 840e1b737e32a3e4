"""Reuse one loaded procedural scene: more views, an opaque camera, emitters rescaled in place.

Dr.Jit compiles a new kernel for every new scene (each object's material becomes code; a fresh
``mi.load_dict`` of the very same dict compiles again, measured), and compilation dominates the
cost of a small image. So :mod:`mcdenoise.render.procedural_dataset` loads each drawn scene once
and renders all of its views, previews and references from that one object, changing only values
that reach the kernels as *opaque* parameters (measured with ``dr.JitFlag.KernelHistory``, Mitsuba
3.9 on LLVM):

* the camera's ``to_world``: a literal when loaded or set from a plain ``mi.Transform4f`` (a new
  view recompiles everything, 1.6 s for a 12-object scene); after :func:`set_camera` it is an
  opaque variable and any later camera reuses the kernels;
* area/point/spot radiance: opaque already, so :func:`scale_loaded_emitters` rescales them
  without recompiling (indoor scenes: the preview's kernel is the input's). An envmap's
  ``scale`` changes the kernel with its value; its pixel data does so less often (after a first
  update, which the generator does before the preview, some scenes keep their kernel, others
  still compile once more: not understood). Mitsuba's ``sunsky`` keeps
  ``sun_scale``/``sky_scale`` as scalars baked into the kernel. So outdoor scenes usually
  compile their input kernel twice (preview, then after the exposure fix), once per scene;
* the sampler seed and the row offset (already opaque in :mod:`mcdenoise.render.api`). The image
  size and the spp are literals: a preview shares the input's kernel only at the input's size
  and spp.

Views (:func:`view_camera`) keep the scene's field of view and lens (both are literals too): an
indoor view is a new camera anywhere in the room looking across it, an outdoor view orbits the
drawn camera's target by 10-45 degrees, since outdoor objects are only placed around that view.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mcdenoise.render.procedural.camera import _roll_up
from mcdenoise.render.procedural.scene import ProceduralScene
from mcdenoise.render.procedural.transforms import look_at

__all__ = ["set_camera", "scale_loaded_emitters", "view_camera", "view_motion_end", "motion_pixels", "reference_time_slices"]


def set_camera(scene: Any, camera_to_world: np.ndarray) -> None:
    """Pose the first sensor of a loaded scene at ``camera_to_world`` (4x4), as an opaque value.

    Later poses then reuse the kernels compiled for this one instead of compiling new ones.
    """
    import drjit as dr

    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    m = np.asarray(camera_to_world, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"camera_to_world: expected a finite 4x4 matrix, got shape {m.shape}")
    params = mi.traverse(scene.sensors()[0])
    t = mi.Transform4f(m.tolist())
    dr.make_opaque(t)
    params["to_world"] = t
    # A thin-lens camera's aperture and focus distance load as literals; the first update after a
    # render evaluates them into kernel inputs, which compiled the scene once more (issue 18,
    # measured: the outdoor envmap scenes' exposure fix). Same values, opaque from the start.
    for key in params.keys():
        v = params[key]
        if type(v) is mi.Float and dr.width(v) == 1:
            v = mi.Float(v)
            dr.make_opaque(v)
            params[key] = v
    params.update()


def scale_loaded_emitters(scene: Any, scene_dict: dict, k: float = 1.0) -> list[str]:
    """Bring the loaded ``scene``'s emitters to the strengths of ``scene_dict``, which the caller
    has just multiplied by ``k`` (1 = only make them opaque, before the first render).

    Only the top-level emitters the generator makes are handled (area lights on shapes, point,
    spot, envmap, sunsky), found by their ids. Area, point and spot radiance become the dict's
    float32-rounded numbers, as opaque values. An envmap's ``scale`` is left as loaded (a new
    value changes the kernel, measured) and its pixel data is multiplied by ``k`` instead (same
    image up to rounding; so ``k`` must be the factor since the previous call). Sunsky scales are scalars baked into the kernel: set from the dict,
    they cost one compilation. Returns the parameter keys that were set.
    """
    import drjit as dr

    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    params = mi.traverse(scene)
    keys = set(params.keys())
    done: list[str] = []

    def colour(key: str, value: list[float]) -> None:
        c = mi.Color3f(*[float(v) for v in value])
        dr.make_opaque(c)
        params[key] = c
        done.append(key)

    for sid, node in scene_dict.items():
        if not isinstance(node, dict):
            continue
        t = node.get("type")
        if isinstance(node.get("emitter"), dict) and node["emitter"].get("type") == "area":
            colour(f"{sid}.emitter.radiance.value", node["emitter"]["radiance"]["value"])
        elif t in ("point", "spot"):
            colour(f"{sid}.intensity.value", node["intensity"]["value"])
        elif t == "envmap":
            # Also with k = 1, before the preview, so that every update leaves the same state.
            # (The recompile once blamed on this update was the thin-lens camera's literals,
            # made opaque in set_camera since; data * k is kept: datasets stay bit-identical.)
            params[f"{sid}.data"] = params[f"{sid}.data"] * float(k)
            done.append(f"{sid}.data")
        elif t == "sunsky":
            # Not ``k``: that is the factor, still needed by an envmap later in the dict.
            for name in ("sun_scale", "sky_scale"):
                params[f"{sid}.{name}"] = float(node.get(name, 1.0))
                done.append(f"{sid}.{name}")
    missing = [key for key in done if key not in keys]
    if missing:
        raise KeyError(f"scale_loaded_emitters: the loaded scene has no parameter(s) {missing}")
    params.update()
    return done


def _clear(p: np.ndarray, extents: dict[str, tuple[np.ndarray, float]], margin: float, factor: float = 1.0) -> bool:
    return all(float(np.linalg.norm(p - c)) > factor * r + margin for c, r in extents.values())


def view_camera(ps: ProceduralScene, rng: np.random.Generator) -> np.ndarray:
    """Camera-to-world (4x4) of another view of the drawn scene ``ps``, drawn from ``rng``.

    Indoors: a position in the room (0.4 m from the walls, 0.8-2 m high) clear of every object
    and furniture piece, looking across the room, as the drawn camera does. Outdoors: the drawn
    camera orbited about its target by 10-45 degrees either way, 0.75-1.25 times as far, 0.5-3 m
    above the ground plane, clear of the objects. Up to 20 tries for a clear position; the last
    one is kept otherwise (the caller's preview check rejects a view that shows nothing).
    """
    origin, target, _ = (np.asarray(v, dtype=np.float64) for v in ps.camera_path)
    if ps.kind == "indoor" and ps.room is not None:
        hx, hz, h = ps.room
        for _ in range(20):
            pos = np.array([rng.uniform(-hx + 0.4, hx - 0.4), rng.uniform(0.8, min(2.0, h - 0.3)),
                            rng.uniform(-hz + 0.4, hz - 0.4)])
            if _clear(pos, ps.extents, 0.3):
                break
        far = -np.sign(pos[[0, 2]]) * np.array([hx, hz]) * rng.uniform(0.2, 0.9, 2)
        tgt = np.array([far[0], rng.uniform(0.3, 1.5), far[1]])
    else:
        back = origin - target
        dist = float(np.linalg.norm(back[[0, 2]]))
        heading = math.atan2(back[0], back[2])
        for _ in range(20):
            turn = rng.uniform(math.radians(10), math.radians(45)) * rng.choice([-1.0, 1.0])
            r = dist * rng.uniform(0.75, 1.25)
            pos = np.array([target[0] + r * math.sin(heading + turn), rng.uniform(0.5, 3.0),
                            target[2] + r * math.cos(heading + turn)])
            if _clear(pos, ps.extents, 0.2, factor=2.0):
                break
        tgt = target + rng.normal(0.0, 0.05 * max(dist, 1e-3), 3)
    return look_at(pos, tgt, _roll_up(rng))


def view_motion_end(ps: ProceduralScene, camera_to_world: np.ndarray) -> np.ndarray | None:
    """Camera at shutter close for a view: the drawn camera's motion, expressed in camera space,
    applied to this view (None when the drawn camera does not move)."""
    if ps.camera_to_world_end is None:
        return None
    rel = np.linalg.inv(np.asarray(ps.camera_to_world, dtype=np.float64)) @ np.asarray(ps.camera_to_world_end)
    return np.asarray(camera_to_world, dtype=np.float64) @ rel


def motion_pixels(ps: ProceduralScene, camera_to_world: np.ndarray, width: int) -> float:
    """Largest on-screen travel (pixels) of a moving object over the shutter, seen from
    ``camera_to_world`` with the scene's horizontal field of view on ``width`` pixels.

    Conservative: each object's translation is measured at the depth of its nearest point
    (centre depth minus radius, at least 0.1 m), ignoring the depth component of the motion.
    Objects (partly) behind the camera count as infinite travel.
    """
    if not ps.object_motion:
        return 0.0
    inv = np.linalg.inv(np.asarray(camera_to_world, dtype=np.float64))
    focal = width / 2 / math.tan(math.radians(ps.fov) / 2)  # pixels per unit of x/z
    worst = 0.0
    for oid, tr in ps.object_motion.items():
        centre, radius = ps.extents.get(oid, (None, 0.0))
        if centre is None:
            return math.inf
        depth = float((inv @ np.append(centre, 1.0))[2]) - radius
        if depth < 0.1:
            return math.inf
        d = inv[:3, :3] @ np.asarray(tr, dtype=np.float64)
        worst = max(worst, float(np.hypot(d[0], d[1])) * focal / depth)
    return worst


def reference_time_slices(ps: ProceduralScene, camera_to_world: np.ndarray, width: int,
                          lo: int = 8, hi: int = 256) -> int:
    """Time slices the reference needs so that consecutive slices of any moving object lie at
    most half a pixel apart on screen: ``ceil(2 * motion_pixels)``, clipped to [lo, hi].

    Each slice costs a scene update and a kernel launch whatever its spp, so the renderer's
    default (256) made the reference of a 64x64 image with moving objects cost 10-40x one without
    (measured); slices half a pixel apart are below what the pixel's box filter resolves.
    """
    px = motion_pixels(ps, camera_to_world, width)
    if not math.isfinite(px):
        return hi
    return int(min(hi, max(lo, math.ceil(2.0 * px))))
