"""Render a procedural dataset: many image folders, resumable, shardable, with a manifest.

Layout of a dataset folder ``DIR``::

    dataset.json              the options it was made with (a rerun must agree with them)
    manifest.json             image entries with their scene-level split (rebuilt, atomically)
    proc_000000/              image 0 (one frame), an image folder of the data format
    proc_000001/frame_000/    image 1 of a sequence dataset (``frames > 1``): one folder per frame
    ...

Image ``i`` is drawn from ``derive_seed(seed, i)``, so any machine renders the same image ``i``:
shard ``k/n`` renders the indices with ``i % n == k``, and shards merge by copying their folders
into one ``DIR`` and running ``mcdenoise dataset --merge --out DIR`` (or any rerun), which
rebuilds the manifest from the folders present. Splits are assigned over all ``count`` planned
scenes (:func:`mcdenoise.data.dataset.assign_splits`), so they do not change as images arrive.

Every image folder is written under a hidden temporary name and renamed when complete; a killed
job leaves only hidden ``.proc_*`` leftovers, which the next run of the same shard deletes before
it renders the missing images. Finished folders are never rendered again.
"""

from __future__ import annotations

import gc
import json
import re
import shutil
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Callable

import numpy as np

from mcdenoise.data.format import read_json_document
from mcdenoise.errors import FormatError, SceneError
from mcdenoise.io.atomic import atomic_file

__all__ = [
    "DatasetConfig",
    "CONFIG_FILE",
    "scene_name",
    "image_paths",
    "shard_indices",
    "finished_paths",
    "clean_partial",
    "rebuild_manifest",
    "render_dataset",
    "render_procedural_image",
]

CONFIG_FILE = "dataset.json"
_NAME = re.compile(r"^proc_(\d{6,})$")
_FRAME = re.compile(r"^frame_(\d{3,})$")


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

    def check(self) -> None:
        from mcdenoise.render.procedural import KINDS

        for name, lo, hi in (("count", 1, 10**7), ("spp", 1, 1 << 20), ("ref_spp", 0, 1 << 20),
                             ("width", 1, 16384), ("height", 1, 16384), ("frames", 1, 100000), ("max_depth", 1, 1024)):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise SceneError(f"dataset: {name}={v!r} is out of range [{lo}, {hi}]")
        if self.kind is not None and self.kind not in KINDS:
            raise SceneError(f"dataset: kind {self.kind!r} is not one of {', '.join(KINDS)}")
        lo, hi = self.objects
        if not 1 <= lo <= hi <= 1000:
            raise SceneError(f"dataset: objects {lo}-{hi} must satisfy 1 <= min <= max <= 1000")
        fr = tuple(float(f) for f in self.fractions)
        if len(fr) != 3 or min(fr) < 0 or sum(fr) <= 0:
            raise SceneError(f"dataset: split fractions {self.fractions} must be three non-negative numbers")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["fractions"] = list(self.fractions)
        d["objects"] = list(self.objects)
        return {"format": "mcdenoise-procedural-dataset", "version": 1, **d}

    @classmethod
    def from_json(cls, d: dict[str, Any], where: Path) -> "DatasetConfig":
        if not isinstance(d, dict) or d.get("format") != "mcdenoise-procedural-dataset":
            raise FormatError(where, "not a procedural dataset config (format field)")
        names = {f.name for f in fields(cls)}
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


def _write_config(root: Path, cfg: DatasetConfig) -> None:
    """Create ``dataset.json``, or check that an existing one holds the same options."""
    old = _read_config(root)
    if old is not None:
        diff = [f"{f.name}: {getattr(old, f.name)!r} there, {getattr(cfg, f.name)!r} asked"
                for f in fields(cfg) if getattr(old, f.name) != getattr(cfg, f.name)]
        if diff:
            raise FormatError(root / CONFIG_FILE, "this dataset was made with other options (" + "; ".join(diff)
                              + "); rerun with the same options or use another --out")
        return
    root.mkdir(parents=True, exist_ok=True)
    with atomic_file(root / CONFIG_FILE) as tmp:
        tmp.write_text(json.dumps(cfg.to_json(), indent=1) + "\n")


def _is_finished(folder: Path) -> bool:
    return (folder / "meta.json").is_file()


def finished_paths(root: Path, cfg: DatasetConfig) -> set[str]:
    """Relative paths of the complete image folders under ``root`` (within ``cfg.count``)."""
    out: set[str] = set()
    if not root.is_dir():
        return out
    for entry in root.iterdir():
        m = _NAME.match(entry.name)
        if not m or not entry.is_dir() or int(m.group(1)) >= cfg.count:
            continue
        if cfg.frames == 1:
            if _is_finished(entry):
                out.add(entry.name)
            continue
        for sub in entry.iterdir():
            fm = _FRAME.match(sub.name)
            if fm and int(fm.group(1)) < cfg.frames and _is_finished(sub):
                out.add(f"{entry.name}/{sub.name}")
    return out


def clean_partial(root: Path, indices: list[int]) -> list[Path]:
    """Delete hidden leftovers of killed runs (``.proc_000012.*``, ``proc_000012/.frame_003.*``)
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
    entries = []
    for path in sorted(done):
        scene = path.split("/", 1)[0]
        e: dict[str, Any] = {"path": path, "scene": scene, "split": splits[scene], "index": int(scene[5:])}
        if "/" in path:
            e["frame"] = int(path.rsplit("_", 1)[1])
        entries.append(e)
    return write_manifest(root, entries)


def render_procedural_image(
    cfg: DatasetConfig,
    root: Path,
    index: int,
    todo: list[str],
    *,
    on_image: Callable[[str], None] | None = None,
) -> None:
    """Draw scene ``index`` and render its frames listed in ``todo`` (relative paths)."""
    from mcdenoise.render import RenderSettings, load_scene, render_image
    from mcdenoise.render.procedural import derive_seed, generate
    from mcdenoise.render.sequence import camera_path, motion_vectors, primary_hits

    scene_seed = derive_seed(cfg.seed, index)
    t0 = time.perf_counter()
    ps = generate(scene_seed, kind=cfg.kind, width=cfg.width, height=cfg.height, objects=tuple(cfg.objects))
    t1 = time.perf_counter()
    scene = load_scene(ps.scene, width=cfg.width, height=cfg.height)
    t2 = time.perf_counter()
    name = scene_name(index)
    meta: dict[str, Any] = {
        "procedural": {
            "dataset_seed": cfg.seed,
            "index": index,
            "seed": ps.seed,
            "drawn_seed": ps.drawn_seed,
            "attempts": ps.attempts,
            **ps.info,
            # Drawing + preview check (its JIT compilation included), and the scene load.
            "generate_seconds": round(t1 - t0, 3),
            "load_seconds": round(t2 - t1, 3),
        }
    }
    if cfg.frames == 1:
        settings = RenderSettings(
            spp=cfg.spp, ref_spp=cfg.ref_spp, width=cfg.width, height=cfg.height,
            seed=derive_seed(scene_seed, 0, 1), max_depth=cfg.max_depth,
            object_motion={k: tuple(v) for k, v in ps.object_motion.items()} or None,
            camera_to_world_end=ps.camera_to_world_end,
        )
        render_image(scene, root / name, settings, scene_name=name, extra_meta=meta)
        if on_image is not None:
            on_image(name)
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
        settings = RenderSettings(
            spp=cfg.spp, ref_spp=cfg.ref_spp, width=cfg.width, height=cfg.height,
            seed=derive_seed(scene_seed, f, 1), max_depth=cfg.max_depth,
        )
        prev = path[f - 1] if f > 0 else path[f]
        if f == 0:  # no previous frame: no motion (exactly)
            motion = np.zeros((2, cfg.height, cfg.width), np.float32)
        else:
            pos, hit, dirs = primary_hits(scene, path[f], ps.fov, cfg.width, cfg.height)
            motion = motion_vectors(pos, hit, dirs, prev, ps.fov, cfg.width, cfg.height)
        frame_meta = {**meta, "frame": f, "frames": cfg.frames, "camera_to_world_prev": np.asarray(prev).tolist()}
        render_image(scene, root / rel, settings, scene_name=name, extra_meta=frame_meta,
                     camera_to_world=path[f], record_position=True, extra_noisy={"motion": motion})
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
) -> dict[str, Any]:
    """Render the missing images of shard ``shard/shards`` into ``root``; returns a summary.

    Rebuilds the manifest after each image and at the end (from a fresh scan, which picks up
    folders other shards wrote meanwhile).
    """
    from tqdm import tqdm

    root = Path(root)
    cfg.check()
    if root.exists() and not root.is_dir():
        raise SceneError(f"{root}: exists and is not a folder")
    _write_config(root, cfg)
    indices = shard_indices(cfg.count, shard, shards)
    removed = clean_partial(root, indices)
    done = finished_paths(root, cfg)
    todo = {i: [p for p in image_paths(cfg, i) if p not in done] for i in indices}
    todo = {i: ps for i, ps in todo.items() if ps}
    total = sum(len(v) for v in todo.values())
    skipped = len(indices) * cfg.frames - total
    if log is not None:
        log(f"{root}: shard {shard}/{shards}: {total} image(s) to render, {skipped} already done"
            + (f", removed {len(removed)} partial leftover(s)" if removed else ""))
    t0 = time.perf_counter()
    bar = tqdm(total=total, unit="img", disable=not progress, dynamic_ncols=True)

    def finished(rel: str) -> None:
        done.add(rel)
        rebuild_manifest(root, done)
        bar.update(1)

    try:
        for i, rels in todo.items():
            render_procedural_image(cfg, root, i, rels, on_image=finished)
            # The scene's Mitsuba objects must die before the next scene compiles: Dr.Jit's
            # virtual calls cover every live BSDF of the process.
            gc.collect()
    finally:
        bar.close()
    manifest = rebuild_manifest(root)
    return {"rendered": total, "skipped": skipped, "removed_partial": len(removed),
            "seconds": time.perf_counter() - t0, "manifest": str(manifest)}
