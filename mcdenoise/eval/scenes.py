"""Evaluate on a folder of scene files with given references (issue 19: the third-party set).

A scenes folder holds one Mitsuba 3 scene per sub-folder (``NAME/scene.xml``) or loose ``*.xml``
files; a references folder holds ``NAME_<W>[x<H>]_spp<N>_d<D>.npy`` files (``H x W x 3`` linear RGB
radiance, float16 or float32), as ``shared/valscenes/refs`` does. For each scene with a
reference, the inputs are rendered once at the reference's size and max depth (a normal image
folder, with the reference stored in it) into a work folder, and reused by later runs when
their settings match. The scenes and references are only read, never written.
"""

from __future__ import annotations

import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mcdenoise.errors import McDenoiseError

__all__ = ["SceneCase", "ScenesError", "find_scene_cases", "prepare_scene_inputs"]

_REF = re.compile(r"^(?P<name>.+)_(?P<w>\d+)(?:x(?P<h>\d+))?_spp(?P<spp>\d+)_d(?P<d>\d+)\.npy$")


class ScenesError(McDenoiseError):
    """A scenes or references folder that cannot be used as asked."""


@dataclass(frozen=True)
class SceneCase:
    """One scene file and the reference it is scored against."""

    name: str
    scene_file: Path
    reference: Path
    width: int
    height: int
    reference_spp: int
    max_depth: int

    def folder_name(self, spp: int, seed: int) -> str:
        return f"{self.name}_{self.width}x{self.height}_d{self.max_depth}_spp{spp}_seed{seed}"


def _scene_files(scenes: Path) -> dict[str, Path]:
    if not scenes.is_dir():
        raise ScenesError(f"{scenes}: not a folder of scene files")
    found: dict[str, Path] = {}
    for sub in sorted(scenes.iterdir()):
        if sub.is_dir() and (sub / "scene.xml").is_file():
            found[sub.name] = sub / "scene.xml"
        elif sub.is_file() and sub.suffix == ".xml":
            found[sub.stem] = sub
    return found


def find_scene_cases(scenes: str | Path, refs: str | Path | None = None, *, names: list[str] | None = None) -> list[SceneCase]:
    """Pair the scene files of ``scenes`` with references in ``refs`` (default ``scenes/refs``).

    With several references for one scene (sizes, depths), the largest spp at the smallest size
    is used. Scenes without a reference are left out with a note on stderr; none at all is an error.
    """
    scenes = Path(scenes)
    refs = Path(refs) if refs is not None else scenes / "refs"
    files = _scene_files(scenes)
    if not refs.is_dir():
        raise ScenesError(f"{refs}: no references folder (NAME_<W>_spp<N>_d<D>.npy files)")
    best: dict[str, SceneCase] = {}
    for f in sorted(refs.glob("*.npy")):
        m = _REF.match(f.name)
        if not m or m["name"] not in files:
            continue
        w = int(m["w"])
        h = int(m["h"]) if m["h"] else w
        case = SceneCase(m["name"], files[m["name"]], f, w, h, int(m["spp"]), int(m["d"]))
        old = best.get(case.name)
        if old is None or (case.width * case.height, -case.reference_spp) < (old.width * old.height, -old.reference_spp):
            best[case.name] = case
    missing = sorted(set(files) - set(best))
    if names:
        unknown = sorted(set(names) - set(best))
        if unknown:
            raise ScenesError(f"{scenes}: no scene with a reference named {', '.join(unknown)} (have {', '.join(sorted(best))})")
        best = {n: best[n] for n in names}
        missing = []
    if missing:
        print(f"eval: {refs}: no reference for {', '.join(missing)}; left out", file=sys.stderr)
    if not best:
        raise ScenesError(f"{scenes}: none of its {len(files)} scene(s) has a reference in {refs}")
    return [best[n] for n in sorted(best)]


def load_reference(case: SceneCase) -> np.ndarray:
    """``(3, H, W)`` float32 radiance of ``case``'s reference; a one-line error if it is unusable."""
    try:
        arr = np.load(case.reference, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise ScenesError(f"{case.reference}: not a readable .npy array ({e})") from None
    if arr.shape != (case.height, case.width, 3):
        raise ScenesError(f"{case.reference}: shape {arr.shape}, expected ({case.height}, {case.width}, 3) from its name")
    arr = arr.astype(np.float32).transpose(2, 0, 1)
    if not np.isfinite(arr).all() or (arr < 0).any():
        raise ScenesError(f"{case.reference}: non-finite or negative radiance")
    return np.ascontiguousarray(arr)


#: Inputs rendered before the canonical emitter order (render/emitter_order.py) lack this mark; their
#: scenes with mesh emitters (kitchen, spaceship, coffee) hold one draw of a load-dependent order, so
#: they are rendered again once, and from then on come back the same on every run.
EMITTER_SAMPLING = "canonical-order"


def _matches(folder: Path, case: SceneCase, spp: int, seed: int) -> bool:
    from mcdenoise.data.image_folder import ImageFolder
    from mcdenoise.errors import McDenoiseError

    try:
        ImageFolder(folder)  # readable by this version (checksums, format)
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, ValueError, McDenoiseError):
        return False
    extra = meta.get("extra", {})
    return (meta.get("width"), meta.get("height"), meta.get("spp"), meta.get("seed"), extra.get("max_depth"),
            extra.get("reference_file"), extra.get("emitter_sampling")) == (
        case.width, case.height, spp, seed, case.max_depth, case.reference.name, EMITTER_SAMPLING)


def prepare_scene_inputs(cases: list[SceneCase], work: str | Path, *, spp: int, seed: int = 7,
                         progress: bool = True) -> list[Path]:
    """Image folders of ``cases`` rendered at ``spp`` with ``seed`` under ``work`` (made when missing).

    Each folder holds the per-sample inputs and the case's reference; a folder left by an earlier
    run with the same settings is reused, a stale one is replaced (only one mcdenoise wrote).
    """
    from mcdenoise.render import RenderSettings, load_scene, render_image

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    out: list[Path] = []
    for case in cases:
        folder = work / case.folder_name(spp, seed)
        if _matches(folder, case, spp, seed):
            out.append(folder)
            continue
        ref = load_reference(case)
        scene = load_scene(case.scene_file, width=case.width, height=case.height)
        settings = RenderSettings(spp=spp, ref_spp=0, width=case.width, height=case.height, seed=seed,
                                  max_depth=case.max_depth)
        settings.check()
        if progress:
            print(f"eval: rendering {case.name} at {spp} spp ({case.width}x{case.height}, max depth {case.max_depth})",
                  file=sys.stderr)
        render_image(scene, folder, settings, scene_name=case.name, overwrite=folder.exists(),
                     extra_meta={"source": str(case.scene_file), "reference_file": case.reference.name,
                                 "emitter_sampling": EMITTER_SAMPLING},
                     reference=({"radiance": ref}, case.reference_spp))
        del scene
        out.append(folder)
    return out
