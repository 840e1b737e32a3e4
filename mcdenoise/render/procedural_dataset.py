"""Render a procedural dataset: many image folders, resumable, shardable, with a manifest.

Layout of a dataset folder ``DIR``::

    dataset.json              the options it was made with, the Mitsuba variant included (a rerun
                              must agree with them)
    manifest.json             image entries with their scene-level split, and the options of
                              dataset.json under "settings" (rebuilt, atomically)
    proc_000000/              image 0 (one frame), an image folder of the data format
    proc_000001/frame_000/    image 1 of a sequence dataset (``frames > 1``): one folder per frame
    proc_000002/view_001/     view 1 of scene 2 (``views > 1``): one folder per view
    ...

Image ``i`` is drawn from ``derive_seed(seed, i)``, so any machine renders the same image ``i``:
shard ``k/n`` renders the indices with ``i % n == k``, and shards merge by copying their folders
into one ``DIR`` and running ``mcdenoise dataset --merge --out DIR`` (or any rerun), which
rebuilds the manifest from the folders present. Splits are assigned over all ``count`` planned
scenes (:func:`mcdenoise.data.dataset.assign_splits`), so they do not change as images arrive.

Every image folder is written under a hidden temporary name and renamed when complete; a killed
job leaves only hidden ``.proc_*`` leftovers, which the next run of the same shard deletes before
it renders the missing images. Finished folders are never rendered again.

Cost: each new scene compiles its own kernels (seconds; see :mod:`mcdenoise.render.procedural.views`).
A scene is therefore loaded once and everything is rendered from that one object: the rejection
preview (same size, spp and motion as the input, so it compiles the input's kernel), every view
(``views``, cameras set as opaque values) and every reference.
"""

from __future__ import annotations

import gc
import json
import math
import re
import shutil
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mcdenoise.data.format import read_json_document
from mcdenoise.errors import FormatError, SceneError
from mcdenoise.io.safety import DEFAULT_MAX_BYTES, WriterLock, atomic_file, check_space

__all__ = [
    "DatasetConfig",
    "CONFIG_FILE",
    "scene_name",
    "image_paths",
    "shard_indices",
    "finished_paths",
    "clean_partial",
    "rebuild_manifest",
    "recorded_variant",
    "images_variant",
    "RENDER_VARIANTS",
    "render_dataset",
    "render_procedural_image",
]

CONFIG_FILE = "dataset.json"
_NAME = re.compile(r"^proc_(\d{6,})$")
_SUB = re.compile(r"^(frame|view)_(\d{3,})$")
#: Version of the drawing + preview + exposure pipeline. Images of one dataset must all come from
#: one version (2: preview on the loaded scene with the input's settings; 1: 32-pixel preview
#: with Mitsuba's path integrator); a dataset.json without the field was made by version 1.
GENERATOR = 2
#: Mitsuba variants a dataset may record (``mcdenoise.render._mitsuba.VARIANTS`` less ``auto``).
RENDER_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
#: Camera draws per extra view before falling back to the drawn (already checked) camera.
VIEW_ATTEMPTS = 8


@dataclass
class DatasetConfig:
    """Options of a procedural dataset; stored in ``dataset.json``.

    Attributes:
        count: number of scenes (images, or sequences when ``frames > 1``).
        seed: dataset seed; scene ``i`` uses ``derive_seed(seed, i)``.
        spp: samples per pixel of the per-sample input.
        ref_spp: samples per pixel of the reference (0 = none).
        width, height: image size in pixels.
        frames: frames per scene; > 1 renders a camera path with ``position`` and ``motion``.
        max_depth: path depth (Mitsuba's convention), input and reference alike.
        kind: ``"indoor"``, ``"outdoor"`` or None (both, half each on average).
        fractions: train/val/test fractions of the scene-level split.
        objects: (min, max) objects per scene (fewer compile faster; SBMC used up to 50).
        views: camera views rendered per scene (each its own image, seed and check); the
            scene's kernels compile once for all of them. Not combined with ``frames > 1``.
        generator: version of the scene pipeline (:data:`GENERATOR`); recorded so that a rerun
            never mixes images of two versions into one dataset.
        world: ``classic`` (the original generator) or ``rich`` (window-lit rooms, small bright
            emitters, night scenes, exposure over 2.3 decades: issue 19).
        variant: the Mitsuba variant the images are rendered with (``llvm_ad_rgb`` on a CPU,
            ``cuda_ad_rgb`` on a GPU: they give other pixels for the same seed). None: the
            process's variant, recorded in dataset.json when the dataset is created; a
            dataset.json written before the field existed has none (its images' meta.json name it).
    """

    count: int
    seed: int = 0
    spp: int = 8
    ref_spp: int = 1024
    width: int = 128
    height: int = 128
    frames: int = 1
    max_depth: int = 6
    kind: str | None = None
    fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)
    objects: tuple[int, int] = (10, 50)
    views: int = 1
    generator: int = GENERATOR
    world: str = "classic"
    variant: str | None = None

    def check(self) -> None:
        from mcdenoise.render.procedural import KINDS

        for name, lo, hi in (("count", 1, 10**7), ("spp", 1, 1 << 20), ("ref_spp", 0, 1 << 20),
                             ("width", 1, 16384), ("height", 1, 16384), ("frames", 1, 100000), ("max_depth", 1, 1024), ("views", 1, 10000)):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise SceneError(f"dataset: {name}={v!r} is out of range [{lo}, {hi}]")
        if not 0 <= int(self.seed) < 2**32:
            raise SceneError(f"dataset: seed {self.seed} must be in [0, {2**32 - 1}] (seeds are 32-bit)")
        if self.views > 1 and self.frames > 1:
            raise SceneError("dataset: views > 1 and frames > 1 cannot be combined (a sequence is one view)")
        if self.generator != GENERATOR:
            raise SceneError(f"dataset: made by scene pipeline version {self.generator}; this mcdenoise renders "
                             f"version {GENERATOR} (render a new dataset)")
        from mcdenoise.render.procedural.rich import WORLDS

        if self.world not in WORLDS:
            raise SceneError(f"dataset: world {self.world!r} is not one of {', '.join(WORLDS)}")
        if self.variant is not None and self.variant not in RENDER_VARIANTS:
            raise SceneError(f"dataset: Mitsuba variant {self.variant!r} is not one of {', '.join(RENDER_VARIANTS)}")
        if self.kind is not None and self.kind not in KINDS:
            raise SceneError(f"dataset: kind {self.kind!r} is not one of {', '.join(KINDS)}")
        lo, hi = self.objects
        if not 1 <= lo <= hi <= 1000:
            raise SceneError(f"dataset: objects {lo}-{hi} must satisfy 1 <= min <= max <= 1000")
        fr = tuple(float(f) for f in self.fractions)
        if len(fr) != 3 or not all(math.isfinite(f) for f in fr) or min(fr) < 0 or sum(fr) <= 0:
            raise SceneError(f"dataset: split fractions {self.fractions} must be three non-negative numbers")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["fractions"] = list(self.fractions)
        d["objects"] = list(self.objects)
        if d["variant"] is None:  # not recorded: the file keeps the form of older versions
            del d["variant"]
        return {"format": "mcdenoise-procedural-dataset", "version": 1, **d}

    def settings(self) -> dict[str, Any]:
        """Every option that decides the pixels (the variant included): the ``settings`` block
        of manifest.json, so the manifest's SHA-256 (which names a run's data) covers them."""
        return {k: v for k, v in self.to_json().items() if k not in ("format", "version")}

    @classmethod
    def from_json(cls, d: dict[str, Any], where: Path) -> "DatasetConfig":
        if not isinstance(d, dict) or d.get("format") != "mcdenoise-procedural-dataset":
            raise FormatError(where, "not a procedural dataset config (format field)")
        names = {f.name for f in fields(cls)}
        d = {"generator": 1, **d}  # written before the field existed
        try:
            cfg = cls(**{k: v for k, v in d.items() if k in names})
        except TypeError as e:
            raise FormatError(where, f"bad config ({e})") from None
        cfg.fractions = tuple(cfg.fractions)  # type: ignore[assignment]
        cfg.objects = tuple(cfg.objects)  # type: ignore[assignment]
        return cfg


def scene_name(index: int) -> str:
    return f"proc_{index:06d}"


def image_paths(cfg: DatasetConfig, index: int) -> list[str]:
    """Folder paths (relative to the dataset root) of the frames of scene ``index``."""
    name = scene_name(index)
    if cfg.views > 1:
        return [f"{name}/view_{v:03d}" for v in range(cfg.views)]
    if cfg.frames == 1:
        return [name]
    return [f"{name}/frame_{f:03d}" for f in range(cfg.frames)]


def shard_indices(count: int, shard: int = 0, shards: int = 1) -> list[int]:
    """The scene indices shard ``shard`` of ``shards`` renders: ``i % shards == shard``."""
    if shards < 1 or not 0 <= shard < shards:
        raise SceneError(f"--shard {shard}/{shards}: need 0 <= i < n")
    return list(range(shard, count, shards))


def _read_config(root: Path) -> DatasetConfig | None:
    path = root / CONFIG_FILE
    if not path.exists():
        return None
    return DatasetConfig.from_json(read_json_document(path), path)


def images_variant(root: str | Path) -> str | None:
    """The Mitsuba variant named by the first image's meta.json under ``root`` (None: no image,
    or one that names none). Datasets made before dataset.json recorded the variant."""
    from mcdenoise.render._mitsuba import variant_of_renderer

    root = Path(root)
    for meta in sorted([*root.glob("proc_*/meta.json"), *root.glob("proc_*/*_*/meta.json")]):
        try:
            doc = json.loads(meta.read_text())
        except (OSError, ValueError):
            continue
        found = variant_of_renderer(str(doc.get("renderer", ""))) if isinstance(doc, dict) else None
        if found is not None:
            return found
    return None


def recorded_variant(root: str | Path) -> str | None:
    """The variant a procedural dataset was rendered with: its dataset.json's, else (older
    datasets) its images', else None."""
    cfg = _read_config(Path(root))
    if cfg is not None and cfg.variant is not None:
        return cfg.variant
    return images_variant(root)


def _write_config(root: Path, cfg: DatasetConfig) -> None:
    """Create ``dataset.json``, or check that an existing one holds the same options.

    A dataset.json without a variant (written by an older version) is left as it is, so its
    manifest, and the manifest hash runs trained on it recorded, stay the same; its images must
    then name the variant asked for (when they name one)."""
    old = _read_config(root)
    if old is not None:
        diff = [f"{f.name}: {getattr(old, f.name)!r} there, {getattr(cfg, f.name)!r} asked"
                for f in fields(cfg) if getattr(old, f.name) != getattr(cfg, f.name)
                and not (f.name == "variant" and old.variant is None)]
        if old.variant is None and cfg.variant is not None:
            there = images_variant(root)
            if there is not None and there != cfg.variant:
                diff.append(f"variant: {there!r} in its images, {cfg.variant!r} asked (--variant {there})")
        if diff:
            raise FormatError(root / CONFIG_FILE, "this dataset was made with other options (" + "; ".join(diff)
                              + "); rerun with the same options or use another --out")
        return
    root.mkdir(parents=True, exist_ok=True)
    with atomic_file(root / CONFIG_FILE) as tmp:
        tmp.write_text(json.dumps(cfg.to_json(), indent=1) + "\n")


def _is_finished(folder: Path) -> bool:
    """A complete, undamaged-looking image: meta.json present and the folder opens (sizes, headers;
    a truncated samples.bin is not finished). Full checksums: :func:`mcdenoise.data.verify.verify_image`."""
    if not (folder / "meta.json").is_file():
        return False
    from mcdenoise.data.verify import verify_image

    return verify_image(folder, full=False) is None


def finished_paths(root: Path, cfg: DatasetConfig) -> set[str]:
    """Relative paths of the complete image folders under ``root`` (within ``cfg.count``)."""
    out: set[str] = set()
    if not root.is_dir():
        return out
    for entry in root.iterdir():
        m = _NAME.match(entry.name)
        if not m or not entry.is_dir() or int(m.group(1)) >= cfg.count:
            continue
        if cfg.frames == 1 and cfg.views == 1:
            if _is_finished(entry):
                out.add(entry.name)
            continue
        want, limit = ("view", cfg.views) if cfg.views > 1 else ("frame", cfg.frames)
        for sub in entry.iterdir():
            fm = _SUB.match(sub.name)
            if fm and fm.group(1) == want and int(fm.group(2)) < limit and _is_finished(sub):
                out.add(f"{entry.name}/{sub.name}")
    return out


def clean_partial(root: Path, indices: list[int]) -> list[Path]:
    """Delete hidden leftovers of killed runs (``.proc_000012.*``, ``proc_000012/.frame_003.*``,
    ``proc_000012/.view_001.*``)
    that belong to ``indices`` only, so shards sharing a folder never touch each other's work."""
    mine = {scene_name(i) for i in indices}
    removed: list[Path] = []
    if not root.is_dir():
        return removed
    for entry in root.iterdir():
        if entry.name.startswith(".proc_") and entry.name[1:].split(".", 1)[0] in mine:
            removed.append(entry)
        elif entry.name in mine and entry.is_dir():
            # The writer's temporary folders ``.frame_003.tmp-*``.
            removed.extend(sub for sub in entry.iterdir() if sub.name.startswith("."))
    for p in removed:
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    return removed


def rebuild_manifest(root: str | Path, done: set[str] | None = None) -> Path:
    """Write ``root/manifest.json`` from the finished folders (scanned when ``done`` is None)."""
    from mcdenoise.data.dataset import assign_splits, write_manifest

    root = Path(root)
    cfg = _read_config(root)
    if cfg is None:
        raise FormatError(root / CONFIG_FILE, "no such file (not a procedural dataset folder?)")
    done = finished_paths(root, cfg) if done is None else done
    splits = assign_splits([scene_name(i) for i in range(cfg.count)], cfg.fractions, cfg.seed)
    # Datasets whose dataset.json records no variant (older versions) keep the old manifest
    # form, byte for byte: runs trained on them recorded its SHA-256 and resume against it.
    settings = cfg.settings() if cfg.variant is not None else None
    entries = []
    for path in sorted(done):
        scene = path.split("/", 1)[0]
        e: dict[str, Any] = {"path": path, "scene": scene, "split": splits[scene], "index": int(scene[5:])}
        if "/" in path:
            kind, num = path.rsplit("/", 1)[1].split("_")
            e[kind] = int(num)
        entries.append(e)
    return write_manifest(root, entries, settings=settings)


def _settings(cfg: DatasetConfig, seed: int, *, ps: Any = None, camera: Any = None, camera_end: Any = None) -> Any:
    """Render settings of one image; with ``ps`` (and its view's ``camera``) the scene's motion,
    and a reference time-slice count fitted to the on-screen motion."""
    from mcdenoise.render import RenderSettings
    from mcdenoise.render.procedural.views import reference_time_slices

    motion = {k: tuple(v) for k, v in ps.object_motion.items()} if ps is not None else {}
    slices = reference_time_slices(ps, camera, cfg.width) if motion else RenderSettings.ref_time_slices
    return RenderSettings(spp=cfg.spp, ref_spp=cfg.ref_spp, width=cfg.width, height=cfg.height, seed=seed,
                          max_depth=cfg.max_depth, object_motion=motion or None, camera_to_world_end=camera_end,
                          ref_time_slices=slices)


def _view(cfg: DatasetConfig, ps: Any, scene_seed: int, view: int, rejected: list[str]) -> tuple[np.ndarray, Any]:
    """Camera (4x4) and render settings of view ``view`` >= 1 of the drawn scene ``ps``.

    Camera ``attempt`` of the view is drawn from ``derive_seed(scene_seed, 3, view, attempt)``, so
    a view never depends on which other views were rendered (shards, resume). Each is checked with
    the same preview as the scene (on the loaded scene, same kernel); after VIEW_ATTEMPTS
    rejections the drawn camera is used with the view's own seed.
    """
    from mcdenoise.render.procedural import derive_seed, preview_stats
    from mcdenoise.render.procedural.views import set_camera, view_camera, view_motion_end

    for attempt in range(VIEW_ATTEMPTS):
        c2w = view_camera(ps, np.random.default_rng(derive_seed(scene_seed, 3, view, attempt)))
        settings = _settings(cfg, derive_seed(scene_seed, view, 1), ps=ps, camera=c2w, camera_end=view_motion_end(ps, c2w))
        set_camera(ps.loaded, c2w)
        problem = preview_stats(ps, scene=ps.loaded, settings=settings, seed=derive_seed(scene_seed, 9, view, attempt)).problem()
        if problem is None:
            return c2w, settings
        rejected.append(f"camera {attempt}: {problem}")
    c2w = np.asarray(ps.camera_to_world)
    return c2w, _settings(cfg, derive_seed(scene_seed, view, 1), ps=ps, camera=c2w, camera_end=ps.camera_to_world_end)


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
        ps = generate(scene_seed, kind=cfg.kind, width=cfg.width, height=cfg.height, objects=tuple(cfg.objects), world=cfg.world,
                      settings=view0, keep_loaded=True)
    else:
        ps = generate(scene_seed, kind=cfg.kind, width=cfg.width, height=cfg.height, objects=tuple(cfg.objects), world=cfg.world,
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
        for v, rel in enumerate(image_paths(cfg, index)):
            if rel not in todo:
                continue
            tv = time.perf_counter()
            rejected: list[str] = []
            if v == 0:
                c2w = np.asarray(ps.camera_to_world)
                settings = view0(ps)
            else:
                c2w, settings = _view(cfg, ps, scene_seed, v, rejected)
            set_camera(scene, c2w)
            view_meta = dict(meta)
            if cfg.views > 1:
                view_meta["view"] = {"index": v, "views": cfg.views, "rejected_cameras": rejected,
                                     "check_seconds": round(time.perf_counter() - tv, 3)}
            extra = {**view_meta, "camera_to_world": c2w.tolist()}
            if settings.object_motion:
                extra["ref_time_slices"] = min(settings.ref_time_slices, settings.ref_spp)
            # overwrite: only a damaged leftover of ours can be there (finished images are not todo).
            render_image(scene, root / rel, settings, scene_name=name, extra_meta=extra, overwrite=True, **write_opts)
            if on_image is not None:
                on_image(rel)
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


def render_dataset(
    root: str | Path,
    cfg: DatasetConfig,
    *,
    shard: int = 0,
    shards: int = 1,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    nonfinite: str = "sanitize",
    max_bytes: int | None = DEFAULT_MAX_BYTES,
) -> dict[str, Any]:
    """Render the missing images of shard ``shard/shards`` into ``root``; returns a summary.

    Rebuilds the manifest after each image and at the end (from a fresh scan, which picks up
    folders other shards wrote meanwhile).
    """
    from dataclasses import replace

    from mcdenoise.render._mitsuba import process_variant, set_variant

    root = Path(root)
    cfg.check()
    # The variant is fixed here (before any render) and recorded: a GPU renders other pixels.
    cfg = replace(cfg, variant=cfg.variant or process_variant())
    set_variant(cfg.variant)
    if root.exists() and not root.is_dir():
        raise SceneError(f"{root}: exists and is not a folder")
    indices = shard_indices(cfg.count, shard, shards)
    # One writer per shard of a folder: a second run of the same (or an overlapping) shard is
    # refused; disjoint shards may share the folder. Taken before dataset.json is written.
    lock = WriterLock(root / f".lock.shard-{shard}-of-{shards}", f"shard {shard}/{shards}",
                      pattern=".lock.shard-*", conflicts=lambda doc: _shards_overlap(doc, shard, shards))
    with lock:
        return _render_dataset_locked(root, cfg, indices, shard=shard, shards=shards, progress=progress, log=log,
                                      nonfinite=nonfinite, max_bytes=max_bytes)


def _shards_overlap(doc: dict[str, Any], shard: int, shards: int) -> bool:
    """Whether another lock's shard ``i/n`` shares an index with ``shard/shards`` (i = shard mod
    gcd(n, shards) has a solution by the Chinese remainder theorem); unknown holders overlap."""
    m = re.match(r"^shard (\d+)/(\d+)$", str(doc.get("what", "")))
    if not m:
        return True
    i, n = int(m.group(1)), int(m.group(2))
    return (i - shard) % math.gcd(n, shards) == 0


def _render_dataset_locked(root: Path, cfg: DatasetConfig, indices: list[int], *, shard: int, shards: int,
                           progress: bool, log: Callable[[str], None] | None, nonfinite: str,
                           max_bytes: int | None) -> dict[str, Any]:
    from tqdm import tqdm

    from mcdenoise.data.format import ImageMeta
    from mcdenoise.data.samples_header import _samples_header
    from mcdenoise.data.writer import estimate_exr_bytes
    from mcdenoise.render import SAMPLE_CHANNELS

    _write_config(root, cfg)
    removed = clean_partial(root, indices)
    done = finished_paths(root, cfg)
    todo = {i: [p for p in image_paths(cfg, i) if p not in done] for i in indices}
    todo = {i: ps for i, ps in todo.items() if ps}
    total = sum(len(v) for v in todo.values())
    skipped = sum(len(image_paths(cfg, i)) for i in indices) - total
    if log is not None:
        log(f"{root}: shard {shard}/{shards}: {total} image(s) to render, {skipped} already done"
            + (f", removed {len(removed)} partial leftover(s)" if removed else ""))
    probe = ImageMeta(width=cfg.width, height=cfg.height, spp=cfg.spp, channels=list(SAMPLE_CHANNELS))
    per_image = _samples_header(probe, 32, "auto")[1] + estimate_exr_bytes(probe)
    check_space(root, per_image * total, max_bytes=max_bytes, what=f"{total} image(s) of {cfg.width}x{cfg.height} at {cfg.spp} spp")
    t0 = time.perf_counter()
    bar = tqdm(total=total, unit="img", disable=not progress, dynamic_ncols=True)

    def finished(rel: str) -> None:
        done.add(rel)
        rebuild_manifest(root, done)
        bar.update(1)

    try:
        for i, rels in todo.items():
            render_procedural_image(cfg, root, i, rels, on_image=finished, nonfinite=nonfinite, max_bytes=max_bytes)
            # The scene's Mitsuba objects must die before the next scene compiles: Dr.Jit's
            # virtual calls cover every live BSDF of the process.
            gc.collect()
    finally:
        bar.close()
    manifest = rebuild_manifest(root)
    return {"rendered": total, "skipped": skipped, "removed_partial": len(removed),
            "seconds": time.perf_counter() - t0, "manifest": str(manifest)}
