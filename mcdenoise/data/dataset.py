"""A dataset: a folder of image folders plus ``manifest.json`` with a scene-level split.

``manifest.json``::

    {"format": "mcdenoise-dataset", "version": 1,
     "settings": {"spp": 16, "ref_spp": 1024, "width": 128, ..., "variant": "llvm_ad_rgb"},
     "images": [{"path": "scene_a/0000", "scene": "scene_a", "split": "train", ...}, ...]}

``settings`` (procedural datasets whose dataset.json records the Mitsuba variant) holds every
option that decides the pixels, so the manifest's SHA-256, which names the data a run trained on,
changes with them and not only with the image list. Older manifests have no ``settings`` and keep
their bytes (and hash) when rebuilt.

Every image of a scene is in the same split (the writer and the reader both refuse otherwise), so
no test scene leaks into training through another view or seed of it.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from mcdenoise.data.format import FORMAT_VERSION, META_FILE, ImageFolder, read_json_document
from mcdenoise.errors import FormatError
from mcdenoise.io.atomic import atomic_file

__all__ = ["SPLITS", "MANIFEST_FILE", "assign_splits", "write_manifest", "read_manifest", "read_manifest_settings", "Dataset",
           "dataset_dirs"]

SPLITS = ("train", "val", "test")
MANIFEST_FILE = "manifest.json"


def dataset_dirs(spec: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """The dataset folders of a ``--data`` value: one folder, several separated by commas
    (``data/a,data/b``), or a list of folders."""
    if isinstance(spec, (list, tuple)):
        return [Path(p) for p in spec]
    parts = [p.strip() for p in str(spec).split(",")]
    if not all(parts):
        raise ValueError(f"--data {spec!r}: an empty dataset name between commas")
    return [Path(p) for p in parts]


def _scene_key(scene: str, seed: int) -> str:
    # A hash, not Python's hash(): stable across runs and machines.
    return hashlib.sha256(f"{seed}:{scene}".encode()).hexdigest()


def assign_splits(
    scenes: Sequence[str], fractions: tuple[float, float, float] = (0.8, 0.1, 0.1), seed: int = 0
) -> dict[str, str]:
    """Scene -> ``"train"|"val"|"test"``, deterministic in (set of scenes, fractions, seed).

    Scenes are ordered by a SHA-256 hash of ``f"{seed}:{scene}"``; the first
    ``round(n * f_test)`` go to test, the next ``round(n * f_val)`` to val, the rest to train. A split
    with a positive fraction gets at least one scene when there are at least three scenes.
    Duplicates in ``scenes`` are ignored.
    """
    if len(fractions) != 3 or any(f < 0 for f in fractions) or sum(fractions) <= 0:
        raise ValueError(f"fractions must be three non-negative numbers, got {fractions}")
    total = float(sum(fractions))
    f_train, f_val, f_test = (f / total for f in fractions)
    uniq = sorted(set(scenes), key=lambda s: _scene_key(s, seed))
    n = len(uniq)
    n_test, n_val = round(n * f_test), round(n * f_val)
    if n >= 3:
        n_test = max(n_test, 1 if f_test > 0 else 0)
        n_val = max(n_val, 1 if f_val > 0 else 0)
        if f_train > 0:
            while n_test + n_val > n - 1:
                if n_val >= n_test and n_val > 0:
                    n_val -= 1
                else:
                    n_test -= 1
    out = {}
    for i, s in enumerate(uniq):
        out[s] = "test" if i < n_test else "val" if i < n_test + n_val else "train"
    return out


def _check_entries(where: str | os.PathLike, entries: list[dict[str, Any]]) -> None:
    split_of: dict[str, str] = {}
    seen: set[str] = set()
    for i, e in enumerate(entries):
        if not isinstance(e, dict):
            raise FormatError(where, f"image #{i} is not an object")
        for key in ("path", "scene", "split"):
            if not isinstance(e.get(key), str) or not e[key]:
                raise FormatError(where, f"image #{i} has no {key!r}")
        if e["split"] not in SPLITS:
            raise FormatError(where, f"image {e['path']!r}: split {e['split']!r} is not one of {SPLITS}")
        p = Path(e["path"])
        if p.is_absolute() or ".." in p.parts:
            raise FormatError(where, f"image path {e['path']!r} must be relative and inside the dataset")
        if e["path"] in seen:
            raise FormatError(where, f"image {e['path']!r} listed twice")
        seen.add(e["path"])
        prev = split_of.setdefault(e["scene"], e["split"])
        if prev != e["split"]:
            raise FormatError(where, f"scene {e['scene']!r} is in two splits ({prev} and {e['split']})")


def write_manifest(root: str | os.PathLike, entries: list[dict[str, Any]], *,
                   settings: dict[str, Any] | None = None) -> Path:
    """Write ``root/manifest.json`` atomically; refuses a scene in two splits or a bad entry.

    ``entries``: ``{"path": folder relative to root, "scene": id, "split": "train|val|test", ...}``
    (extra keys are kept). ``settings``: the render settings of the images (the ``settings``
    block); None writes none, as older versions did.
    """
    path = Path(root) / MANIFEST_FILE
    _check_entries(path, entries)
    doc: dict[str, Any] = {"format": "mcdenoise-dataset", "version": FORMAT_VERSION}
    if settings is not None:
        doc["settings"] = dict(settings)
    doc["images"] = list(entries)
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def read_manifest(root: str | os.PathLike) -> list[dict[str, Any]]:
    """The validated image entries of ``root/manifest.json``."""
    path = Path(root) / MANIFEST_FILE
    if not path.is_file():
        raise FormatError(path, "no such file (not a dataset folder?)")
    doc = read_json_document(path, "mcdenoise-dataset", "dataset manifest")
    entries = doc.get("images")
    if not isinstance(entries, list):
        raise FormatError(path, "no 'images' list")
    _check_entries(path, entries)
    return entries


def read_manifest_settings(root: str | os.PathLike) -> dict[str, Any] | None:
    """The ``settings`` block of ``root/manifest.json`` (None for a manifest without one)."""
    path = Path(root) / MANIFEST_FILE
    doc = read_json_document(path, "mcdenoise-dataset", "dataset manifest")
    settings = doc.get("settings")
    if settings is not None and not isinstance(settings, dict):
        raise FormatError(path, "'settings' is not an object")
    return settings


class Dataset:
    """A dataset folder: validates the manifest and that every listed image folder exists."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        self.entries = read_manifest(self.root)
        for e in self.entries:
            if not (self.root / e["path"] / META_FILE).is_file():
                raise FormatError(self.root / e["path"] / META_FILE, "no such file (listed in manifest.json)")

    def __len__(self) -> int:
        return len(self.entries)

    def __repr__(self) -> str:
        counts = {s: sum(e["split"] == s for e in self.entries) for s in SPLITS}
        return f"Dataset({str(self.root)!r}, images={counts})"

    def _select(self, split: str | None) -> list[dict[str, Any]]:
        if split is not None and split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; choose one of {SPLITS}")
        return [e for e in self.entries if split is None or e["split"] == split]

    def images(self, split: str | None = None) -> list[ImageFolder]:
        """Open the image folders of ``split`` (all when None), in manifest order."""
        return [ImageFolder(self.root / e["path"]) for e in self._select(split)]

    def paths(self, split: str | None = None) -> list[Path]:
        return [self.root / e["path"] for e in self._select(split)]

    def scenes(self, split: str | None = None) -> list[str]:
        """Sorted scene ids of ``split``."""
        return sorted({e["scene"] for e in self._select(split)})
