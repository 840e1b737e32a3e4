"""What a procedural dataset folder holds: finished image folders, leftovers of killed runs, and
the manifest rebuilt from the finished folders (layout: :mod:`mcdenoise.render.procedural_dataset`).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path
from typing import Any

from mcdenoise.errors import FormatError
from mcdenoise.render.dataset_config import CONFIG_FILE, DatasetConfig, _read_config, scene_name

__all__ = ["finished_paths", "clean_partial", "rebuild_manifest"]

_NAME = re.compile(r"^proc_(\d{6,})$")
_SUB = re.compile(r"^(frame|view)_(\d{3,})$")


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
