"""A drawn scene description (:mod:`mcdenoise.render.cycles.draw`) built with ``bpy``.

Runs only in the Cycles worker process (``bpy`` is imported by the caller and passed in).
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["build_scene"]

_TEX_NODES = {"checker": "ShaderNodeTexChecker", "noise": "ShaderNodeTexNoise", "voronoi": "ShaderNodeTexVoronoi",
              "wave": "ShaderNodeTexWave", "brick": "ShaderNodeTexBrick", "magic": "ShaderNodeTexMagic"}


def _rgba(c: list[float]) -> tuple[float, float, float, float]:
    return (float(c[0]), float(c[1]), float(c[2]), 1.0)


def _texture(nodes: Any, links: Any, tex: dict[str, Any]) -> Any:
    """The texture's colour output: two colours mixed by a procedural pattern."""
    node = nodes.new(_TEX_NODES[tex["type"]])
    # World position: the scale is per metre on every object (generated coordinates would
    # stretch a pattern over a 60 m ground).
    links.new(nodes.new("ShaderNodeNewGeometry").outputs["Position"], node.inputs["Vector"])
    node.inputs["Scale"].default_value = tex["scale"]
    if "Detail" in node.inputs:
        node.inputs["Detail"].default_value = tex["detail"]
    if tex["type"] in ("checker", "brick"):
        node.inputs["Color1"].default_value = _rgba(tex["a"])
        node.inputs["Color2"].default_value = _rgba(tex["b"])
        return node.outputs["Color"]
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = _rgba(tex["a"])
    ramp.color_ramp.elements[1].color = _rgba(tex["b"])
    fac = node.outputs["Fac"] if "Fac" in node.outputs else node.outputs["Distance"]
    links.new(fac, ramp.inputs["Fac"])
    return ramp.outputs["Color"]


def make_material(bpy: Any, name: str, m: dict[str, Any]) -> Any:
    """A Principled BSDF material for one drawn material (kinds: :data:`draw.MATERIALS`)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = _rgba(m["colour"])
    bsdf.inputs["Roughness"].default_value = m["roughness"]
    kind = m["kind"]
    if kind in ("metal", "mirror"):
        bsdf.inputs["Metallic"].default_value = 1.0
    elif kind == "glass":
        bsdf.inputs["Transmission Weight"].default_value = 1.0
        bsdf.inputs["IOR"].default_value = m["ior"]
    elif kind == "emissive":
        bsdf.inputs["Emission Color"].default_value = _rgba(m["colour"])
        bsdf.inputs["Emission Strength"].default_value = m["strength"]
    if "texture" in m:
        links.new(_texture(nodes, links, m["texture"]), bsdf.inputs["Base Color"])
    return mat


def _add(bpy: Any, shape: str, material: Any, size: float, location: list[float], rotation: list[float]) -> Any:
    op = getattr(bpy.ops.mesh, f"primitive_{shape}_add")
    r = size / 2
    kw = {"uv_sphere": {"radius": r, "segments": 48, "ring_count": 24}, "ico_sphere": {"radius": r, "subdivisions": 2},
          "cube": {"size": size}, "cylinder": {"radius": r, "depth": size}, "cone": {"radius1": r, "depth": size},
          "torus": {"major_radius": r * 0.7, "minor_radius": r * 0.3}, "monkey": {"size": size}}[shape]
    op(location=tuple(location), rotation=tuple(rotation), **kw)
    obj = bpy.context.object
    obj.data.materials.append(material)
    if shape in ("uv_sphere", "torus", "cylinder", "cone", "monkey"):
        bpy.ops.object.shade_smooth()
    return obj


def _box(bpy: Any, material: Any, centre: tuple[float, float, float], dims: tuple[float, float, float]) -> None:
    bpy.ops.mesh.primitive_cube_add(size=1, location=centre, scale=dims)
    bpy.context.object.data.materials.append(material)


def _room(bpy: Any, r: dict[str, Any]) -> None:
    """Six walls of thickness 0.1 around the room's inside; the window is a hole in one of them."""
    w, d, h, t = r["width"], r["depth"], r["height"], 0.1
    floor, walls, ceiling = (make_material(bpy, n, r[n]) for n in ("floor", "walls", "ceiling"))
    _box(bpy, floor, (0, 0, -t / 2), (w + 2 * t, d + 2 * t, t))
    _box(bpy, ceiling, (0, 0, h + t / 2), (w + 2 * t, d + 2 * t, t))
    _box(bpy, walls, (0, -d / 2 - t / 2, h / 2), (w + 2 * t, t, h))  # behind the camera
    win = r["window"]
    for name, (cx, cy, along_x, length) in {"back": (0.0, d / 2 + t / 2, True, w),
                                             "left": (-w / 2 - t / 2, 0.0, False, d),
                                             "right": (w / 2 + t / 2, 0.0, False, d)}.items():
        def piece(u0: float, u1: float, z0: float, z1: float) -> None:
            if u1 - u0 < 1e-3 or z1 - z0 < 1e-3:
                return
            u, z = (u0 + u1) / 2, (z0 + z1) / 2
            centre = (u, cy, z) if along_x else (cx, u, z)
            dims = (u1 - u0, t, z1 - z0) if along_x else (t, u1 - u0, z1 - z0)
            _box(bpy, walls, centre, dims)

        if win is None or win["wall"] != name:
            piece(-length / 2, length / 2, 0, h)
            continue
        a, b = win["offset"] - win["width"] / 2, win["offset"] + win["width"] / 2
        z0, z1 = win["sill"], win["sill"] + win["height"]
        piece(-length / 2, a, 0, h)
        piece(b, length / 2, 0, h)
        piece(a, b, 0, z0)
        piece(a, b, z1, h)


def _world(bpy: Any, scene: Any, wd: dict[str, Any]) -> None:
    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    scene.world = world
    if wd["type"] == "plain":
        bg.inputs["Color"].default_value = _rgba(wd["colour"])
        bg.inputs["Strength"].default_value = wd["strength"]
        return
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    sky.sky_type = "NISHITA"
    sky.sun_elevation = math.radians(wd["elevation"])
    sky.sun_rotation = math.radians(wd["rotation"])
    sky.sun_disc = False  # the sun is the lamp below, sampled as a light
    world.node_tree.links.new(sky.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = wd["sky_strength"]
    # The lamp shines along -z rotated: x by (90 - elevation), z by (rotation - 90), as the sky's sun.
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(90.0 - wd["elevation"]), 0,
                                                   math.radians(wd["rotation"] - 90.0)))
    sun = bpy.context.object
    sun.data.energy = wd["sun_strength"]
    sun.data.angle = math.radians(wd["sun_angle"])


def _look_at(obj: Any, location: list[float], target: list[float]) -> None:
    import mathutils  # bundled with bpy

    direction = mathutils.Vector([t - l for t, l in zip(target, location)])
    obj.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()


def _lights(bpy: Any, lights: list[dict[str, Any]]) -> None:
    for li in lights:
        bpy.ops.object.light_add(type=li["type"], location=tuple(li["location"]))
        obj = bpy.context.object
        obj.data.energy = li["energy"]
        if li["type"] == "AREA":
            obj.data.size = li["size"]
            obj.rotation_euler = (0, 0, 0)  # an area light shines along its -z: down from the ceiling
        else:
            obj.data.shadow_soft_size = li["radius"]
        if li["type"] == "SPOT":
            obj.data.spot_size = math.radians(li["spot_size"])
            _look_at(obj, li["location"], li["target"])
        obj.visible_camera = li["visible"]
        obj.visible_glossy = True


def build_scene(bpy: Any, desc: dict[str, Any]) -> Any:
    """Empty the Blender session and build ``desc`` in it; returns the scene."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if desc["kind"] == "room":
        _room(bpy, desc["room"])
    else:
        _add(bpy, "cube", make_material(bpy, "floor", desc["floor"]), 1.0, [0, 0, -0.05], [0, 0, 0])
        bpy.context.object.scale = (60, 60, 0.1)
    for i, o in enumerate(desc["objects"]):
        _add(bpy, o["shape"], make_material(bpy, f"m{i}", o["material"]), o["size"], o["location"], o["rotation"])
    _lights(bpy, desc["lights"])
    _world(bpy, scene, desc["world"])
    cam_d = desc["camera"]
    bpy.ops.object.camera_add(location=tuple(cam_d["location"]))
    cam = bpy.context.object
    _look_at(cam, cam_d["location"], cam_d["target"])
    cam.data.lens = cam_d["lens"]
    cam.data.clip_start = 0.02
    if "dof" in cam_d:
        cam.data.dof.use_dof = True
        cam.data.dof.aperture_fstop = cam_d["dof"]["fstop"]
        cam.data.dof.focus_distance = cam_d["dof"]["distance"]
    scene.camera = cam
    return scene
