"""Render one scene of a procedural dataset: draw it, load it once, and render its views or the
frames of its camera path from that one loaded scene (each view checked by a preview first).

Costs and why a scene is loaded once: :mod:`mcdenoise.render.procedural_dataset`.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mcdenoise.render.dataset_config import DatasetConfig, image_paths, scene_name

__all__ = ["render_procedural_image"]

#: Camera draws per extra view before falling back to the drawn (already checked) camera.
VIEW_ATTEMPTS = 8
#: Samples per pixel of a camera check, per generator: 3 checks an extra view at 4 spp, 4 checks
#: every view (the scene's preview too) at 1 spp. The kernel is the input's either way (the sample
#: count is not a literal of it); the statistics are measured on pixel blocks
#: (:func:`check_settings`), so that black and dim fractions see about the input's noise.
CHECK_SPP = {3: 4, 4: 1}


def check_settings(cfg: DatasetConfig, settings: Any, *, first_view: bool = False) -> tuple[Any, int]:
    """``(settings, block)`` of a camera check: the input's own under generator 2 (and for the
    scene's preview, ``first_view``, under 3); else :data:`CHECK_SPP` and a block side that restores
    about the input's samples per measured value (generator 3: 16 spp -> 4 spp on 2x2 blocks; 4: 16
    spp -> 1 spp on 4x4 blocks). A check of a scene with moving objects renders one time slice per
    sample: at 1 spp, one scene update and one kernel launch instead of the input's 16.

    Measured (``bench_dataset.py --size 256 --spp 16 --views 16``): the check at the input's
    settings cost as much as the input itself (2.5-5.9 s per view); see docs/DATASETS.md.
    """
    spp = CHECK_SPP.get(cfg.generator)
    if spp is None or (first_view and cfg.generator < 4) or settings.spp <= spp:
        return settings, 1
    return replace(settings, spp=spp), max(1, min(4, round((settings.spp / spp) ** 0.5)))



def _settings(cfg: DatasetConfig, seed: int, *, ps: Any = None, camera: Any = None, camera_end: Any = None) -> Any:
    """Render settings of one image; with ``ps`` (and its view's ``camera``) the scene's motion,
    and a reference time-slice count fitted to the on-screen motion."""
    from mcdenoise.render import RenderSettings
    from mcdenoise.render.procedural.views import reference_time_slices

    motion = {k: tuple(v) for k, v in ps.object_motion.items()} if ps is not None else {}
    slices = reference_time_slices(ps, camera, cfg.width) if motion else RenderSettings.ref_time_slices
    return RenderSettings(spp=cfg.spp, ref_spp=cfg.ref_spp, width=cfg.width, height=cfg.height, seed=seed,
                          max_depth=cfg.max_depth, rr_depth=cfg.rr_depth, object_motion=motion or None,
                          camera_to_world_end=camera_end,
                          ref_time_slices=slices)


def _view(cfg: DatasetConfig, ps: Any, scene_seed: int, view: int, rejected: list[str],
          first: str | None = "unchecked") -> tuple[np.ndarray, Any]:
    """Camera (4x4) and render settings of view ``view`` >= 1 of the drawn scene ``ps``.

    Camera ``attempt`` of the view is drawn from ``derive_seed(scene_seed, 3, view, attempt)``, so
    a view never depends on which other views were rendered (shards, resume; under generator 4 its
    camera 0 is checked with its stack, which is fixed by the dataset's options). Each is checked with
    the same preview as the scene (on the loaded scene, same kernel); after VIEW_ATTEMPTS
    rejections the drawn camera is used with the view's own seed. ``first``: the verdict on camera 0
    when it was checked elsewhere (:func:`_stacked_checks`: None = accepted, or the problem).
    """
    from mcdenoise.render.procedural import derive_seed, preview_stats
    from mcdenoise.render.procedural.views import set_camera, view_camera, view_motion_end

    for attempt in range(VIEW_ATTEMPTS):
        c2w = view_camera(ps, np.random.default_rng(derive_seed(scene_seed, 3, view, attempt)))
        settings = _settings(cfg, derive_seed(scene_seed, view, 1), ps=ps, camera=c2w, camera_end=view_motion_end(ps, c2w))
        if attempt == 0 and first != "unchecked":
            if first is None:
                return c2w, settings
            rejected.append(f"camera 0: {first}")
            continue
        set_camera(ps.loaded, c2w)
        check, block = check_settings(cfg, settings)
        problem = preview_stats(ps, scene=ps.loaded, settings=check, seed=derive_seed(scene_seed, 9, view, attempt),
                                block=block, stack_camera=c2w if stacked(cfg) else None).problem()
        if problem is None:
            return c2w, settings
        rejected.append(f"camera {attempt}: {problem}")
    c2w = np.asarray(ps.camera_to_world)
    return c2w, _settings(cfg, derive_seed(scene_seed, view, 1), ps=ps, camera=c2w, camera_end=ps.camera_to_world_end)


#: Generator 4 renders the inputs of a scene's views in stacks (:mod:`mcdenoise.render.view_stack`)
#: of at most this many bytes of per-sample data (counted at 64 floats per sample), so that memory
#: stays bounded: 16 views of 128x128 at 16 spp make one stack, of 256x256 four; from about
#: 512x512 at 16 spp, where two views would not fit, views render one by one.
STACK_BYTES = 1 << 30


def _per_stack(cfg: DatasetConfig) -> int:
    return int(STACK_BYTES // (cfg.width * cfg.height * cfg.spp * 64 * 4))


def stacked(cfg: DatasetConfig) -> bool:
    """Whether the dataset renders its views' inputs in stacks: generator 4, several views, and at
    least two of them within :data:`STACK_BYTES` (a larger image streams its samples to disk band
    by band, one view at a time, as before: a stack holds its views' samples in memory)."""
    return cfg.generator >= 4 and cfg.views > 1 and cfg.frames == 1 and _per_stack(cfg) >= 2


def view_groups(cfg: DatasetConfig) -> list[list[int]]:
    """The views of a scene, in the stacks generator 4 renders together (one view per group before).

    Fixed by the dataset's options alone, so a resumed dataset re-renders exactly the stack of a
    missing view, and gets the same pixels for it (a view's samples depend on its stack)."""
    if not stacked(cfg):
        return [[v] for v in range(cfg.views)]
    per = _per_stack(cfg)
    return [list(range(a, min(cfg.views, a + per))) for a in range(0, cfg.views, per)]


def _stacked_checks(cfg: DatasetConfig, ps: Any, scene_seed: int, views: list[int]) -> dict[int, str | None]:
    """The check of camera 0 of each view in ``views`` (>= 1), all in one view stack at the check's
    spp: view -> None (accepted) or the problem. Seeded ``derive_seed(scene_seed, 9, first view)``.

    Checking the views one by one cost a launch each (0.09 s of a 1.0 s image at 128x128, docs/DATASETS.md)."""
    from mcdenoise.render.procedural import derive_seed
    from mcdenoise.render.procedural.preview import image_stats, object_mask
    from mcdenoise.render.procedural.views import set_camera, view_camera, view_motion_end
    from mcdenoise.render.view_stack import render_view_stack

    cams = [view_camera(ps, np.random.default_rng(derive_seed(scene_seed, 3, v, 0))) for v in views]
    seed = derive_seed(scene_seed, 9, views[0])
    check, block = check_settings(cfg, _settings(cfg, seed, ps=ps, camera=cams[0], camera_end=view_motion_end(ps, cams[0])))
    set_camera(ps.loaded, cams[0])
    stack = render_view_stack(ps.loaded, check, cams, cams[0], seed=seed)
    out: dict[int, str | None] = {}
    for i, v in enumerate(views):
        set_camera(ps.loaded, cams[i])
        img = stack[i]["radiance"].mean(axis=0, dtype=np.float64).transpose(1, 2, 0)
        out[v] = image_stats(img, object_mask(ps.loaded, check.width, check.height), block).problem()
    return out


def _render_stack(cfg: DatasetConfig, ps: Any, scene_seed: int, group: list[int],
                  views: dict[int, tuple[np.ndarray, Any, dict[str, Any]]]) -> dict[int, dict[str, np.ndarray]]:
    """Per-sample inputs of the views ``group`` rendered as one stack: view -> name -> (S, C, H, W).

    The sensor is posed at the group's first camera; the stack's seed (samples and slice times)
    is ``derive_seed(scene_seed, 4, first view)``. Each view's meta records the stack."""
    from mcdenoise.render.procedural import derive_seed
    from mcdenoise.render.procedural.views import set_camera
    from mcdenoise.render.reference import render_reference
    from mcdenoise.render.view_stack import render_view_stack

    first = views[group[0]]
    seed = derive_seed(scene_seed, 4, group[0])
    settings = replace(first[1], seed=seed)
    set_camera(ps.loaded, first[0])
    t0 = time.perf_counter()
    out = dict(zip(group, render_view_stack(ps.loaded, settings, [views[v][0] for v in group], first[0], seed=seed)))
    seconds = round(time.perf_counter() - t0, 3)
    ref_seconds = 0.0
    if settings.ref_spp > 0:
        # Every view's reference in one stack too; moving objects get the most time slices any
        # of the views needs (each view's own count before: slices only make it converge better).
        t1 = time.perf_counter()
        slices = max(views[v][1].ref_time_slices for v in group)
        refs = render_reference(ps.loaded, replace(settings, ref_time_slices=slices), stack=([views[v][0] for v in group], first[0]))
        ref_seconds = round(time.perf_counter() - t1, 3)
        for v, ref in zip(group, refs):
            out[v]["reference"] = ref
            if settings.object_motion:
                views[v][2]["ref_time_slices"] = min(slices, settings.ref_spp)
    for v in group:
        views[v][2]["view_stack"] = {"views": [group[0], group[-1] + 1], "seed": seed, "seconds": seconds,
                                     "reference_seconds": ref_seconds}
    return out


def render_procedural_image(
    cfg: DatasetConfig,
    root: Path,
    index: int,
    todo: list[str],
    *,
    on_image: Callable[[str], None] | None = None,
    **write_opts: Any,
) -> None:
    """Draw scene ``index`` and render its frames or views listed in ``todo`` (relative paths).

    The scene is loaded once (by :func:`~mcdenoise.render.procedural.generate`, which checks it
    with the input's own settings); all views, frames and references render from that object.
    ``write_opts`` (``nonfinite``, ``max_bytes``) go to :func:`~mcdenoise.render.render_image`.
    """
    from mcdenoise.render import render_image
    from mcdenoise.render.procedural import derive_seed, generate
    from mcdenoise.render.procedural.views import set_camera
    from mcdenoise.render.sequence import camera_path, motion_vectors, primary_hits

    scene_seed = derive_seed(cfg.seed, index)
    name = scene_name(index)
    t0 = time.perf_counter()
    if cfg.frames == 1:
        # View 0's settings carry the drawn motion, known only once the scene is drawn.
        def view0(ps: Any) -> Any:
            return _settings(cfg, derive_seed(scene_seed, 0, 1), ps=ps, camera=ps.camera_to_world,
                             camera_end=ps.camera_to_world_end)

        def preview0(ps: Any) -> tuple[Any, int]:
            return check_settings(cfg, view0(ps), first_view=True)
        ps = generate(scene_seed, kind=cfg.kind, width=cfg.width, height=cfg.height, objects=tuple(cfg.objects), world=cfg.world,
                      small_emitters=cfg.small_emitters, strong_dof=cfg.strong_dof,
                      settings=preview0, keep_loaded=True, stack=stacked(cfg))
    else:
        ps = generate(scene_seed, kind=cfg.kind, width=cfg.width, height=cfg.height, objects=tuple(cfg.objects), world=cfg.world,
                      small_emitters=cfg.small_emitters, strong_dof=cfg.strong_dof,
                      settings=_settings(cfg, derive_seed(scene_seed, 0, 1)), record_position=True, keep_loaded=True)
    t1 = time.perf_counter()
    scene = ps.loaded
    meta: dict[str, Any] = {
        "procedural": {
            "dataset_seed": cfg.seed,
            "index": index,
            "seed": ps.seed,
            "drawn_seed": ps.drawn_seed,
            "attempts": ps.attempts,
            **ps.info,
            # Drawing + scene load + preview check (which compiles the input's kernels).
            "generate_seconds": round(t1 - t0, 3),
        }
    }
    if cfg.frames == 1:
        paths = image_paths(cfg, index)

        def setup(v: int, first: str | None = "unchecked", shared: float = 0.0) -> tuple[np.ndarray, Any, dict[str, Any]]:
            """View ``v``'s camera (checked; ``first`` and ``shared`` seconds: its stacked check), render settings and meta."""
            tv = time.perf_counter() - shared
            rejected: list[str] = []
            if v == 0:
                c2w, settings = np.asarray(ps.camera_to_world), view0(ps)
            else:
                c2w, settings = _view(cfg, ps, scene_seed, v, rejected, first)
            view_meta = dict(meta)
            if cfg.views > 1:
                view_meta["view"] = {"index": v, "views": cfg.views, "rejected_cameras": rejected,
                                     "check_seconds": round(time.perf_counter() - tv, 3)}
                if cfg.generator >= 3 and (v > 0 or cfg.generator >= 4):
                    check, block = check_settings(cfg, settings, first_view=v == 0)
                    view_meta["view"].update(check_spp=check.spp, check_block=block)
            extra = {**view_meta, "camera_to_world": c2w.tolist()}
            if settings.object_motion:
                extra["ref_time_slices"] = min(settings.ref_time_slices, settings.ref_spp)
            return c2w, settings, extra

        for group in view_groups(cfg):
            if not any(paths[v] in todo for v in group):
                continue
            checked: dict[int, str | None] = {}
            shared = 0.0
            later = [v for v in group if v > 0]
            if stacked(cfg) and later:
                t = time.perf_counter()
                checked = _stacked_checks(cfg, ps, scene_seed, later)
                shared = (time.perf_counter() - t) / len(later)
            views = {v: setup(v, checked.get(v, "unchecked"), shared if v in checked else 0.0) for v in group}
            inputs = _render_stack(cfg, ps, scene_seed, group, views) if stacked(cfg) else {}
            for v in group:
                if paths[v] not in todo:
                    continue
                c2w, settings, extra = views[v]
                set_camera(scene, c2w)
                given = inputs.pop(v, {})
                ref = given.pop("reference", None)
                if ref is not None:  # rendered with the stack: stored as given, not rendered again
                    settings = replace(settings, ref_spp=0)
                    ref = (ref, cfg.ref_spp)
                # overwrite: only a damaged leftover of ours can be there (finished images are not todo).
                render_image(scene, root / paths[v], settings, scene_name=name, extra_meta=extra, overwrite=True,
                             samples=given or None, reference=ref, **write_opts)
                if on_image is not None:
                    on_image(paths[v])
        return
    # A sequence: static scene, camera along a smooth path (in-frame motion blur is off so that
    # frames are consistent and motion vectors describe all the change between frames).
    origin, target, up = ps.camera_path
    rng = np.random.default_rng(derive_seed(scene_seed, 2))
    max_shift = 0.3 if ps.kind == "indoor" else None  # stay inside the room
    path = camera_path(origin, target, up, cfg.frames, rng, max_shift=max_shift)
    (root / name).mkdir(parents=True, exist_ok=True)
    for f, rel in enumerate(image_paths(cfg, index)):
        if rel not in todo:
            continue
        settings = _settings(cfg, derive_seed(scene_seed, f, 1))
        prev = path[f - 1] if f > 0 else path[f]
        if f == 0:  # no previous frame: no motion (exactly)
            motion = np.zeros((2, cfg.height, cfg.width), np.float32)
        else:
            pos, hit, dirs = primary_hits(scene, path[f], ps.fov, cfg.width, cfg.height)
            motion = motion_vectors(pos, hit, dirs, prev, ps.fov, cfg.width, cfg.height)
        frame_meta = {**meta, "frame": f, "frames": cfg.frames, "camera_to_world_prev": np.asarray(prev).tolist(),
                      "camera_to_world": np.asarray(path[f]).tolist()}
        # The camera is set here as an opaque value rather than through render_image's
        # camera_to_world (a literal): every frame then reuses the first frame's kernels.
        set_camera(scene, path[f])
        render_image(scene, root / rel, settings, scene_name=name, extra_meta=frame_meta,
                     record_position=True, extra_noisy={"motion": motion}, overwrite=True, **write_opts)
        if on_image is not None:
            on_image(rel)
