"""Small Cycles scenes built with Blender's Python API (``bpy`` 4.5), for the slow Blender tests.

Every scene is made here from primitives and procedural textures (no downloaded asset), and
rendered the way docs/DENOISE.md tells a Blender 4.x user to: Cycles, *Denoising Data* on, OpenEXR
MultiLayer, float. Run as a script, in its own process (``bpy`` holds one scene per process and
bundles its own Open Image Denoise and TBB, which must not meet pyoidn's in the test process)::

    python tests/blender_scenes.py SCENE OUT.exr --spp N [--size S] [--seed K] [--blender-denoise]
    python tests/blender_scenes.py read IN.exr PASS OUT.exr --size W H   # a pass of IN as Blender reads it

Scenes (:data:`SCENES`), after issue 21:

* ``room`` -- a closed room seen through its open front, a visible area light on the ceiling,
  a glossy metal sphere, a rough glossy cube and a diffuse cylinder on coloured walls.
* ``dof`` -- a chrome sphere over a checker-textured ground under a sun and a Nishita sky,
  camera at f/0.9 focused on the sphere (strong depth of field in front of and behind it).
* ``glass`` -- a glass sphere and a gold torus on a diffuse floor, lit by a point light of
  2 cm diameter hanging in view 20 cm in front of the back wall (seen directly, and in the glass
  and the gold) and a dim grey world.

With ``--blender-denoise`` Blender's own denoiser (OIDN, bundled) runs: the file then has the
noisy colour in ``Noisy Image`` and Blender's result in ``Combined``; without it the noisy colour
is ``Combined`` (and there is no ``Noisy Image``). Rendering uses one CPU thread (the test machine
is shared), so a file is the same on any machine with the same Blender up to Cycles' own changes.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
from pathlib import Path


def _load_recipe():
    """``mcdenoise.render.cycles.recipe`` by its file: a Blender Python (bpy 5.x needs 3.13) need
    not have mcdenoise's dependencies, which importing the package would pull in."""
    path = Path(__file__).resolve().parents[1] / "mcdenoise" / "render" / "cycles" / "recipe.py"
    spec = importlib.util.spec_from_file_location("_mcdenoise_cycles_recipe", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


apply_recipe = _load_recipe().apply_recipe

SCENES = ("room", "dof", "glass")


def _material(bpy, name: str, *, colour=(0.8, 0.8, 0.8), metallic: float = 0.0, roughness: float = 0.5,
              transmission: float = 0.0, ior: float = 1.45):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*colour, 1.0)
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Transmission Weight"].default_value = transmission
    bsdf.inputs["IOR"].default_value = ior
    return mat


def _checker(bpy, name: str, a, b, scale: float):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = 0.6
    tex = nodes.new("ShaderNodeTexChecker")
    tex.inputs["Scale"].default_value = scale
    tex.inputs["Color1"].default_value = (*a, 1.0)
    tex.inputs["Color2"].default_value = (*b, 1.0)
    links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _add(bpy, kind: str, material, **kw):
    getattr(bpy.ops.mesh, f"primitive_{kind}_add")(**kw)
    obj = bpy.context.object
    obj.data.materials.append(material)
    if kind in ("uv_sphere", "torus", "cylinder"):
        bpy.ops.object.shade_smooth()
    return obj


def _camera(bpy, scene, location, target, lens: float = 35.0):
    bpy.ops.object.camera_add(location=location)
    cam = bpy.context.object
    direction = [t - l for t, l in zip(target, location)]
    import mathutils  # bundled with bpy

    cam.rotation_euler = mathutils.Vector(direction).to_track_quat("-Z", "Y").to_euler()
    cam.data.lens = lens
    scene.camera = cam
    return cam


def _world(bpy, scene, colour, strength: float):
    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*colour, 1.0)
    bg.inputs["Strength"].default_value = strength
    scene.world = world
    return world


def build_room(bpy, scene) -> None:
    white = _material(bpy, "white", colour=(0.75, 0.75, 0.72), roughness=0.9)
    red = _material(bpy, "red", colour=(0.7, 0.12, 0.1), roughness=0.9)
    green = _material(bpy, "green", colour=(0.15, 0.6, 0.2), roughness=0.9)
    _add(bpy, "plane", white, size=4, location=(0, 0, 0))                               # floor
    _add(bpy, "plane", white, size=4, location=(0, 0, 3), rotation=(math.pi, 0, 0))     # ceiling
    _add(bpy, "plane", white, size=4, location=(0, 2, 1.5), rotation=(math.pi / 2, 0, 0))   # back
    _add(bpy, "plane", red, size=4, location=(-2, 0, 1.5), rotation=(0, math.pi / 2, 0))     # left
    _add(bpy, "plane", green, size=4, location=(2, 0, 1.5), rotation=(0, -math.pi / 2, 0))   # right
    _add(bpy, "uv_sphere", _material(bpy, "chrome", colour=(0.95, 0.95, 0.95), metallic=1.0, roughness=0.05),
         radius=0.55, location=(-0.7, 0.5, 0.55))
    _add(bpy, "cube", _material(bpy, "glossy", colour=(0.2, 0.3, 0.8), roughness=0.25), size=0.8,
         location=(0.8, 0.6, 0.4), rotation=(0, 0, 0.5))
    _add(bpy, "cylinder", _material(bpy, "clay", colour=(0.8, 0.55, 0.3), roughness=1.0), radius=0.3, depth=1.2,
         location=(0.2, -0.5, 0.6))
    bpy.ops.object.light_add(type="AREA", location=(0, 0.3, 2.98))
    light = bpy.context.object
    light.data.size = 1.0
    light.data.energy = 300.0
    light.visible_camera = True
    _world(bpy, scene, (0.0, 0.0, 0.0), 0.0)
    _camera(bpy, scene, (0, -4.6, 1.6), (0, 0, 1.35), lens=22.0)


def build_dof(bpy, scene) -> None:
    _add(bpy, "plane", _checker(bpy, "ground", (0.8, 0.8, 0.75), (0.1, 0.12, 0.15), scale=24.0), size=40,
         location=(0, 0, 0))
    _add(bpy, "uv_sphere", _material(bpy, "chrome", colour=(0.97, 0.97, 0.97), metallic=1.0, roughness=0.0),
         radius=0.5, location=(0, 0, 0.5), segments=64, ring_count=32)
    _add(bpy, "cube", _material(bpy, "orange", colour=(0.9, 0.4, 0.1), roughness=0.4), size=0.5,
         location=(-1.2, 2.5, 0.25))
    _add(bpy, "uv_sphere", _material(bpy, "blue", colour=(0.1, 0.3, 0.9), roughness=0.3), radius=0.3,
         location=(0.7, -1.3, 0.3))
    world = _world(bpy, scene, (0.0, 0.0, 0.0), 1.0)
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    sky.sky_type = "NISHITA"
    sky.sun_elevation = math.radians(35.0)
    sky.sun_rotation = math.radians(200.0)
    sky.sun_disc = False  # the sun is the lamp below (one sun, sampled as a light)
    world.node_tree.links.new(sky.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.3
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(55.0), 0, math.radians(200.0 - 90.0)))
    sun = bpy.context.object
    sun.data.energy = 4.0
    sun.data.angle = math.radians(1.0)
    cam = _camera(bpy, scene, (0.4, -3.2, 0.9), (0, 0, 0.45), lens=50.0)
    cam.data.dof.use_dof = True
    cam.data.dof.aperture_fstop = 0.9
    cam.data.dof.focus_distance = math.dist((0.4, -3.2, 0.9), (0, 0, 0.5)) - 0.5


def build_glass(bpy, scene) -> None:
    _add(bpy, "plane", _material(bpy, "floor", colour=(0.6, 0.6, 0.6), roughness=0.8), size=12, location=(0, 0, 0))
    _add(bpy, "plane", _material(bpy, "wall", colour=(0.5, 0.55, 0.6), roughness=0.9), size=12,
         location=(0, 1.6, 3), rotation=(math.pi / 2, 0, 0))
    _add(bpy, "uv_sphere", _material(bpy, "glass", colour=(1.0, 1.0, 1.0), roughness=0.0, transmission=1.0,
                                     ior=1.5), radius=0.5, location=(-0.6, 0, 0.5), segments=64, ring_count=32)
    _add(bpy, "torus", _material(bpy, "gold", colour=(1.0, 0.766, 0.336), metallic=1.0, roughness=0.12),
         major_radius=0.45, minor_radius=0.15, location=(0.7, 0.2, 0.15))
    bpy.ops.object.light_add(type="POINT", location=(0.15, 1.4, 1.0))  # in view, 20 cm off the wall
    light = bpy.context.object
    light.data.energy = 20.0
    light.data.shadow_soft_size = 0.01  # radius: a 2 cm light
    light.visible_camera = True
    light.visible_glossy = True
    _world(bpy, scene, (0.5, 0.5, 0.5), 0.15)
    _camera(bpy, scene, (0.3, -3.0, 1.3), (0.1, 0.1, 0.4), lens=45.0)


BUILDERS = {"room": build_room, "dof": build_dof, "glass": build_glass}


def render(scene_name: str, out: str, *, spp: int, size: int = 128, seed: int = 0, blender_denoise: bool = False,
           half: bool = False, border: tuple[float, float, float, float] | None = None,
           light_passes: bool = False) -> None:
    """Build ``scene_name`` in a fresh Blender scene and write ``out`` (OpenEXR MultiLayer, float,
    or half with ``half``); ``border`` = (xmin, xmax, ymin, ymax), fractions of the frame with y
    up, renders and writes only that part (Blender's render region, cropped)."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    BUILDERS[scene_name](bpy, scene)
    # docs/DENOISE.md's Blender 4.x recipe, and this test's own settings: small, deterministic, one
    # CPU thread (the settings the Cycles training data is rendered with, too).
    write_still = apply_recipe(scene, out, spp=spp, size=size, seed=seed, threads=1,
                               blender_denoise=blender_denoise, light_passes=light_passes, half=half)
    if border is not None:
        scene.render.use_border = scene.render.use_crop_to_border = True
        (scene.render.border_min_x, scene.render.border_max_x,
         scene.render.border_min_y, scene.render.border_max_y) = border
    bpy.ops.render.render(write_still=write_still)


def read_pass(src: str, name: str, out: str, size: tuple[int, int]) -> list[str]:
    """Open ``src`` (``size`` = width, height) in Blender as an image, print its passes
    (``passes: A;B;...``, as the compositor's Image node lists them) and write pass ``name``
    through the compositor to ``out`` (OpenEXR, float, no view transform): what a compositor setup
    reading the file gets."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    image = bpy.data.images.load(src)
    scene = bpy.context.scene
    bpy.ops.object.camera_add()
    scene.camera = bpy.context.object
    scene.render.engine = "BLENDER_WORKBENCH"
    blender5 = bpy.app.version >= (5, 0, 0)
    if blender5:  # the compositor is a node group of its own; File Output writes the pass
        tree = bpy.data.node_groups.new("read", "CompositorNodeTree")
        scene.compositing_node_group = tree
        scene.render.compositor_device = "CPU"
    else:
        scene.use_nodes = True
        tree = scene.node_tree
        for node in list(tree.nodes):
            tree.nodes.remove(node)
    node = tree.nodes.new("CompositorNodeImage")
    node.image = image
    passes = [o.name for o in node.outputs]
    print("passes: " + ";".join(passes), flush=True)
    scene.render.resolution_x, scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    if blender5:
        fo = tree.nodes.new("CompositorNodeOutputFile")
        fo.format.media_type = "IMAGE"
        fo.format.file_format = "OPEN_EXR"
        fo.format.color_depth = "32"
        fo.format.color_management = "OVERRIDE"
        fo.format.view_settings.view_transform = "Standard"
        stem = str(Path(out).with_suffix(""))
        fo.directory, fo.file_name = str(Path(stem).parent) + "/", Path(stem).name
        fo.file_output_items.clear()
        fo.file_output_items.new("RGBA", "Image")
        tree.links.new(node.outputs[name], fo.inputs["Image"])
        bpy.ops.render.render(write_still=False)
        Path(f"{stem}Image.exr").replace(out)  # the node appends its input's name in this mode
        return passes
    tree.links.new(node.outputs[name], tree.nodes.new("CompositorNodeComposite").inputs["Image"])
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = out
    bpy.ops.render.render(write_still=True)
    return passes


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["read"]:
        r = argparse.ArgumentParser(description="a pass of an EXR as Blender reads it")
        r.add_argument("src")
        r.add_argument("name")
        r.add_argument("out")
        r.add_argument("--size", type=int, nargs=2, required=True, metavar=("W", "H"))
        a = r.parse_args(argv[1:])
        read_pass(a.src, a.name, a.out, tuple(a.size))
        return 0
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", choices=SCENES)
    p.add_argument("out")
    p.add_argument("--spp", type=int, required=True)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--blender-denoise", action="store_true")
    p.add_argument("--half", action="store_true", help="half-float passes (Blender's 'Float (Half)')")
    p.add_argument("--border", type=float, nargs=4, metavar=("XMIN", "XMAX", "YMIN", "YMAX"),
                   help="render only this region (fractions of the frame, y up), cropped")
    p.add_argument("--light-passes", action="store_true",
                   help="also the Diffuse, Glossy and Transmission Direct/Indirect/Color, Emission and Environment passes")
    args = p.parse_args(argv)
    render(args.scene, args.out, spp=args.spp, size=args.size, seed=args.seed, blender_denoise=args.blender_denoise,
           half=args.half, border=None if args.border is None else tuple(args.border), light_passes=args.light_passes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
