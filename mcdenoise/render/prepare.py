"""Per-render state: the integrator with its roughness table, the sensor, and the motion
bookkeeping (:class:`~mcdenoise.render.prepared._Prepared`), set up before tracing and undone
after it."""

from __future__ import annotations

from typing import Any

import numpy as np

from mcdenoise.errors import SceneError
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.emitter_order import emitter_order
from mcdenoise.render.integrator import INTEGRATOR_NAME
from mcdenoise.render.motion import _pose_objects
from mcdenoise.render.prepared import _Prepared
from mcdenoise.render.scene_loading import _film_size
from mcdenoise.render.settings import RenderSettings


def _bsdf_alpha(bsdf: Any) -> float:
    """GGX alpha of a BSDF for the ``roughness`` channel: its alpha/roughness parameter (texture
    mean), 1 for purely diffuse materials, 0 for smooth (delta) ones."""
    mi = mitsuba()
    flags = int(bsdf.flags())
    params = mi.traverse(bsdf)
    alphas: list[float] = []
    for key in params.keys():
        parts = [p for p in key.split(".") if p not in ("value", "data")]
        if not parts:
            continue
        leaf = parts[-1]
        if leaf in ("alpha", "alpha_u", "alpha_v", "roughness"):
            try:
                v = float(np.mean(np.asarray(params[key], dtype=np.float64)))
            except (TypeError, ValueError):
                continue
            alphas.append(v * v if leaf == "roughness" else v)
    if alphas:
        return float(np.clip(np.mean(alphas), 0.0, 1.0))
    if flags & int(mi.BSDFFlags.Glossy):
        return 0.5
    if flags & int(mi.BSDFFlags.Diffuse):
        return 1.0
    return 0.0


def _roughness_table(scene: Any) -> Any:
    mi = mitsuba()
    import drjit as dr

    entries: dict[int, float] = {}
    for shape in scene.shapes():
        b = shape.bsdf()
        if b is None:
            continue
        rid = int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(b))[0])
        if rid not in entries:
            entries[rid] = _bsdf_alpha(b)
    size = max(entries, default=0) + 1
    table = np.zeros(size, dtype=np.float32)
    for rid, a in entries.items():
        table[rid] = a
    return mi.Float(table)


def _prepare(scene: Any, settings: RenderSettings, camera_to_world: np.ndarray | None) -> _Prepared:
    mi = mitsuba()
    settings.check()
    film = _film_size(scene)
    if film != (settings.width, settings.height):
        # Resizing a loaded film keeps the projection built for the old size (see load_scene).
        raise SceneError(
            f"render settings: {settings.width}x{settings.height} but the scene's film is {film[0]}x{film[1]}: "
            "load the scene at the size to render (load_scene(..., width=, height=))"
        )
    integrator = mi.load_dict({"type": INTEGRATOR_NAME, "max_depth": int(settings.max_depth), "rr_depth": int(settings.rr_depth)})
    integrator.roughness_table = _roughness_table(scene)
    integrator.emitter_order = emitter_order(mi, scene)
    sensor = scene.sensors()[0]
    prep = _Prepared(
        integrator=integrator,
        sensor=sensor,
        width=settings.width,
        height=settings.height,
        has_lens=bool(sensor.needs_aperture_sample()),
        shutter_open=float(sensor.shutter_open()),
        shutter_time=float(sensor.shutter_open_time()),
    )
    sparams = mi.traverse(sensor)
    if camera_to_world is not None:
        m = np.asarray(camera_to_world, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise SceneError(f"camera_to_world: expected a finite 4x4 matrix, got shape {m.shape}")
        prep.restore_camera = mi.Transform4f(sparams["to_world"])
        sparams["to_world"] = mi.Transform4f(m.tolist())
        sparams.update()
    if settings.camera_to_world_end is not None:
        end = np.asarray(settings.camera_to_world_end, dtype=np.float64)
        if end.shape != (4, 4) or not np.all(np.isfinite(end)):
            raise SceneError(f"camera_to_world_end: expected a finite 4x4 matrix, got shape {end.shape}")
        if prep.shutter_time <= 0:
            raise SceneError("camera motion needs a sensor with a shutter (shutter_close > shutter_open)")
        start = np.array(mi.Transform4f(sparams["to_world"]).matrix, dtype=np.float64).reshape(4, 4)
        prep.cam_start, prep.cam_end = start, end
    if settings.object_motion:
        params = mi.traverse(scene)
        keys = set(params.keys())
        for shape_id, tr in settings.object_motion.items():
            tr = np.asarray(tr, dtype=np.float64).reshape(3)
            key = f"{shape_id}.to_world"
            vkey = f"{shape_id}.vertex_positions"
            if key in keys:
                m = np.array(mi.Transform4f(params[key]).matrix, dtype=np.float64).reshape(4, 4)
                prep.motion[key] = (m, tr)
            elif vkey in keys:
                # Meshes without a to_world parameter (cube, obj, ply): move the vertices.
                prep.motion[vkey] = (np.array(params[vkey], dtype=np.float64).reshape(-1, 3), tr)
                nkey = f"{shape_id}.vertex_normals"
                if nkey in keys:
                    normals = np.array(params[nkey], dtype=np.float32).reshape(-1)
                    if normals.size:
                        prep.normals[vkey] = (nkey, normals)
            else:
                movable = sorted({k.rsplit(".", 1)[0] for k in keys if k.endswith((".to_world", ".vertex_positions"))} - {"sensor"})
                raise SceneError(f"object_motion: no movable shape with id {shape_id!r} (movable shapes: {movable})")
        prep.params = params
    return prep


def _restore(scene: Any, prep: _Prepared) -> None:
    mi = mitsuba()
    if prep.motion:
        _pose_objects(prep, 0.0)
    if prep.restore_camera is not None:
        sp = mi.traverse(prep.sensor)
        sp["to_world"] = prep.restore_camera
        sp.update()

