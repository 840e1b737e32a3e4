"""Draw one scene from a seed, unchecked: kind, layout, camera, depth of field and motion.

Motion is not part of the Mitsuba dict (Mitsuba 3 has no moving shapes): it is in
:attr:`~mcdenoise.render.procedural.scene.ProceduralScene.object_motion` (shape id -> translation
over the shutter) and ``camera_to_world_end`` for the renderer to apply.
"""

from __future__ import annotations

import numpy as np

from mcdenoise.errors import SceneError
from mcdenoise.render.procedural.camera import _sensor, _wide_lens
from mcdenoise.render.procedural.detail import Detailer
from mcdenoise.render.procedural.indoor import _indoor
from mcdenoise.render.procedural.objects import MAX_OBJECTS, MIN_OBJECTS, _Builder
from mcdenoise.render.procedural.outdoor import _outdoor
from mcdenoise.render.procedural.rich import WORLDS, enrich
from mcdenoise.render.procedural.scene import ProceduralScene
from mcdenoise.render.procedural.seeds import derive_seed
from mcdenoise.render.procedural.transforms import _rotate, _translate, look_at

__all__ = ["KINDS"]


KINDS = ("indoor", "outdoor")


def _draw(
    seed: int, kind: str | None, width: int, height: int, objects: tuple[int, int] = (MIN_OBJECTS, MAX_OBJECTS),
    world: str = "classic", small_emitters: float | None = None, strong_dof: float | None = None,
) -> ProceduralScene:
    """Draw one scene from ``seed`` without any check; ``world`` is ``classic``, ``rich``
    (:mod:`~mcdenoise.render.procedural.rich`) or ``detailed`` (rich plus
    :mod:`~mcdenoise.render.procedural.detail`), each addition drawn from a stream of its own.

    ``small_emitters``: the probability that a rich or detailed scene keeps the small bright
    emitters it drew (decided from a stream of its own); None keeps them all, as before the option.

    ``strong_dof``: the probability that the scene is shot through a wide lens instead
    (:func:`~mcdenoise.render.procedural.camera._wide_lens`, decided and drawn from a stream of its
    own, so the scene is otherwise the one drawn without it); None: never, as before the option."""
    if world not in WORLDS:
        raise SceneError(f"unknown procedural world {world!r}; worlds: {', '.join(WORLDS)}")
    rng = np.random.default_rng(seed)
    kind = kind or str(rng.choice(KINDS))
    if kind not in KINDS:
        raise SceneError(f"unknown procedural scene kind {kind!r}; kinds: {', '.join(KINDS)}")
    lo, hi = objects
    if not 1 <= lo <= hi <= 1000:
        raise SceneError(f"procedural scene: object count range {lo}-{hi} must satisfy 1 <= min <= max <= 1000")
    b = _Builder(rng)
    detailer = Detailer(np.random.default_rng(derive_seed(seed, 0xDE7A))) if world == "detailed" else None
    b.detail = detailer
    n_objects = int(rng.integers(lo, hi + 1))
    dof = bool(rng.random() < 0.5)
    motion = bool(rng.random() < 0.5)
    cam = (_indoor if kind == "indoor" else _outdoor)(b, n_objects)
    keep_small = small_emitters is None or bool(np.random.default_rng(derive_seed(seed, 0xB01B)).random() < small_emitters)
    rich = enrich(b, kind, np.random.default_rng(derive_seed(seed, 0x51C4)), keep_small) if world != "classic" else None
    if detailer is not None:  # its own stream, meshes first (as drawn): rich draws stay as they are
        assert rich is not None
        rich["detail"] = detailer.finish(b.scene)
    sensor, aperture, focus = _sensor(b, cam, width, height, dof)
    wide = False
    if strong_dof is not None:
        lens_rng = np.random.default_rng(derive_seed(seed, 0xD0F5))
        if lens_rng.random() < strong_dof:
            wide = dof = True
            aperture, focus = _wide_lens(sensor, cam, lens_rng)
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
        **({"wide_lens": wide} if strong_dof is not None else {}),
        "motion_blur": motion,
        "moving_objects": len(obj_motion),
        "camera_motion": cam_close is not None,
    }
    if rich is not None:
        info.update(world=world, rich=rich)
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
