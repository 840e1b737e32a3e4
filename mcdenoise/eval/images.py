"""The images an evaluation runs on: every image with a reference in the data folders given
(datasets, image folders, folders of image folders), each with a unique id and its effects
(depth of field, motion blur)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcdenoise.data.dataset import MANIFEST_FILE, SPLITS, Dataset
from mcdenoise.data.format import META_FILE, ImageFolder
from mcdenoise.errors import EvalError

__all__ = ["EvalImage", "collect_images", "image_effects"]


@dataclass
class EvalImage:
    """One image of the evaluation. ``id`` is unique: ``<data folder name>/<path in it>``."""

    id: str
    folder: ImageFolder
    data: str
    effects: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        m = self.folder.meta
        return {"id": self.id, "path": str(self.folder.path), "data": self.data, "scene": m.scene,
                "width": m.width, "height": m.height, "spp": m.spp, "seed": m.seed, "reference_spp": m.reference_spp,
                "effects": self.effects}


def image_effects(meta: Any) -> list[str]:
    """``depth_of_field`` / ``motion_blur`` when the image has them.

    Procedural images record both flags in ``extra["procedural"]``; other renders (the built-in
    scenes) are judged by their camera's scene features: a lens aperture, an open shutter.
    """
    proc = meta.extra.get("procedural") if isinstance(meta.extra, dict) else None
    f = meta.scene_features
    if isinstance(proc, dict) and "depth_of_field" in proc:
        dof, motion = bool(proc.get("depth_of_field")), bool(proc.get("motion_blur"))
    else:
        dof = float(f.get("aperture_radius", 0.0)) > 0.0
        motion = float(f.get("shutter_close", 0.0)) > float(f.get("shutter_open", 0.0))
    return [name for name, on in (("depth_of_field", dof), ("motion_blur", motion)) if on]


def _folders_of(d: Path, split: str) -> list[tuple[str, ImageFolder]]:
    """(relative id, folder) for a dataset (its ``split``), one image folder, or a folder of them."""
    if (d / MANIFEST_FILE).is_file():
        ds = Dataset(d)
        paths = ds.paths(split)
        if not paths:
            counts = ", ".join(f"{s} {len(ds.paths(s))}" for s in SPLITS)
            raise EvalError(f"{d}: the dataset has no images in the {split!r} split ({counts})")
        return [(p.relative_to(d).as_posix(), ImageFolder(p)) for p in paths]
    if (d / META_FILE).is_file():
        return [(".", ImageFolder(d))]
    subs = sorted(p for p in d.iterdir() if (p / META_FILE).is_file()) if d.is_dir() else []
    if not subs:
        what = "no such folder" if not d.exists() else "neither a dataset (manifest.json), an image folder (meta.json), nor a folder of image folders"
        raise EvalError(f"{d}: {what}")
    return [(p.name, ImageFolder(p)) for p in subs]


def collect_images(data: Sequence[str | os.PathLike], split: str = "test",
                   max_images: int | None = None) -> tuple[list[EvalImage], list[str]]:
    """The images with a reference from each data folder (at most ``max_images`` per folder), and
    notes on what was left out. Raises :class:`EvalError` when a folder gives none."""
    if split not in SPLITS:
        raise EvalError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    if max_images is not None and max_images < 1:
        raise EvalError(f"--max-images must be at least 1, got {max_images}")
    images: list[EvalImage] = []
    notes: list[str] = []
    seen: set[str] = set()
    for d in data:
        d = Path(d)
        found = _folders_of(d, split)
        with_ref = [(rel, f) for rel, f in found if f.has_reference]
        for rel, f in found:
            if not f.has_reference:
                notes.append(f"{f.path}: no reference, left out")
        if not with_ref:
            raise EvalError(f"{d}: none of its {len(found)} image(s) has a reference (reference.exr)")
        if max_images is not None and len(with_ref) > max_images:
            notes.append(f"{d}: first {max_images} of {len(with_ref)} images (--max-images)")
            with_ref = with_ref[:max_images]
        base = d.resolve().name or "data"
        for rel, f in with_ref:
            iid = base if rel == "." else f"{base}/{rel}"
            n = 2
            while iid in seen:  # two data folders of the same name
                iid, n = f"{base}#{n}/{rel}", n + 1
            seen.add(iid)
            images.append(EvalImage(iid, f, str(d), image_effects(f.meta)))
    return images, notes
