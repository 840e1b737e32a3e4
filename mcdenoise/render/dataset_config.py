"""A procedural dataset's options (``dataset.json``), the folder names they give, and the Mitsuba
variant a dataset records.

:class:`DatasetConfig` is what ``dataset.json`` holds; :func:`image_paths` names the image
folders of a scene (``proc_000002``, ``proc_000002/view_001``, ``proc_000001/frame_000``);
:func:`shard_indices` says which scenes a shard renders. The rendering itself:
:mod:`mcdenoise.render.procedural_dataset`.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Collection

import numpy as np

from mcdenoise.data.format import read_json_document
from mcdenoise.errors import FormatError, SceneError
from mcdenoise.io.safety import atomic_file

__all__ = [
    "parse_shard",
    "parse_split",
    "DatasetConfig",
    "CONFIG_FILE",
    "GENERATOR",
    "GENERATORS",
    "RENDER_VARIANTS",
    "scene_name",
    "image_paths",
    "shard_indices",
    "split_indices",
    "SPLITS",
    "recorded_variant",
    "images_variant",
]

CONFIG_FILE = "dataset.json"
#: Version of the drawing + preview + exposure pipeline. Images of one dataset must all come from
#: one version (4: every check, the scene's preview included, at 1 spp measured on blocks of about
#: the input's samples, one time slice when objects move; 3: an extra view's camera is checked at
#: a quarter of the input's spp, measured on 2x2 blocks, with the input's kernel; 2: every check at
#: the input's settings; 1: 32-pixel preview with Mitsuba's path integrator); a dataset.json
#: without the field was made by version 1.
GENERATOR = 4
#: Versions this code renders: new datasets get :data:`GENERATOR`; a dataset made by an older one
#: resumes, and renders again from its recipe, with that version (``--generator``).
GENERATORS = (2, 3, 4)
#: Mitsuba variants a dataset may record (``mcdenoise.render._mitsuba.VARIANTS`` less ``auto``).
RENDER_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")

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
        rr_depth: depth from which Russian roulette may end a path (unbiased), input and reference
            alike; Mitsuba's 5 by default. Earlier is cheaper per sample and noisier
            (docs/DATASETS.md, "Russian roulette"). Recorded only when not 5, so the
            dataset.json and manifest of every dataset made before the field are unchanged.
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
        small_emitters: probability that a scene of the rich or detailed world keeps the small
            bright emitters it drew (docs/DATASETS.md); None: all kept. Recorded only when set,
            so every dataset made before the field keeps its dataset.json and manifest.
        strong_dof: probability that a scene is shot through a wide lens (a blur of 3-19 px at
            infinity for 128 px, the subject in focus; docs/DATASETS.md); None: never. Recorded only
            when set, as ``small_emitters``.
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
    rr_depth: int = 5
    small_emitters: float | None = None
    strong_dof: float | None = None

    def check(self) -> None:
        from mcdenoise.render.procedural import KINDS

        for name, lo, hi in (("count", 1, 10**7), ("spp", 1, 1 << 20), ("ref_spp", 0, 1 << 20),
                             ("width", 1, 16384), ("height", 1, 16384), ("frames", 1, 100000), ("max_depth", 1, 1024), ("views", 1, 10000),
                             ("rr_depth", 1, 1024)):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise SceneError(f"dataset: {name}={v!r} is out of range [{lo}, {hi}]")
        if not 0 <= int(self.seed) < 2**32:
            raise SceneError(f"dataset: seed {self.seed} must be in [0, {2**32 - 1}] (seeds are 32-bit)")
        if self.views > 1 and self.frames > 1:
            raise SceneError("dataset: views > 1 and frames > 1 cannot be combined (a sequence is one view)")
        if self.generator not in GENERATORS:
            raise SceneError(f"dataset: made by scene pipeline version {self.generator}; this mcdenoise renders "
                             f"versions {', '.join(map(str, GENERATORS))} (render a new dataset)")
        from mcdenoise.render.procedural.rich import WORLDS

        if self.world not in WORLDS:
            raise SceneError(f"dataset: world {self.world!r} is not one of {', '.join(WORLDS)}")
        if self.variant is not None and self.variant not in RENDER_VARIANTS:
            raise SceneError(f"dataset: Mitsuba variant {self.variant!r} is not one of {', '.join(RENDER_VARIANTS)}")
        p = self.small_emitters
        if p is not None:
            if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 <= p <= 1:
                raise SceneError(f"dataset: small_emitters={p!r} must be a probability in [0, 1]")
            if self.world == "classic":
                raise SceneError("dataset: small_emitters needs the rich or detailed world (the classic world has none)")
        p = self.strong_dof
        if p is not None and (isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 <= p <= 1):
            raise SceneError(f"dataset: strong_dof={p!r} must be a probability in [0, 1]")
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
        if d["rr_depth"] == 5:  # the default before the field existed: not recorded, as above
            del d["rr_depth"]
        for key in ("small_emitters", "strong_dof"):
            if d[key] is None:  # not recorded, as above
                del d[key]
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


SPLITS = ("train", "val", "test")


def split_indices(cfg: DatasetConfig, indices: list[int], splits: Collection[str]) -> list[int]:
    """Those of ``indices`` whose scene the recipe's split (``cfg.fractions``, ``cfg.seed``) puts
    in one of ``splits``."""
    from mcdenoise.data.dataset import assign_splits

    unknown = sorted(set(splits) - set(SPLITS))
    if unknown or not splits:
        raise SceneError(f"--only-split {','.join(splits)}: expected some of {', '.join(SPLITS)}")
    of = assign_splits([scene_name(i) for i in range(cfg.count)], cfg.fractions, cfg.seed)
    return [i for i in indices if of[scene_name(i)] in splits]


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
                + (f" (--generator {old.generator})" if f.name == "generator" and old.generator in GENERATORS else "")
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


def parse_shard(text: str) -> tuple[int, int]:
    """``"2/8"`` -> (2, 8), checked: 0 <= i < n."""
    i, sep, n = text.partition("/")
    try:
        if not sep:
            raise ValueError
        a, b = int(i), int(n)
    except ValueError:
        raise SceneError(f"--shard {text!r}: expected i/n, e.g. 0/4") from None
    if b < 1 or not 0 <= a < b:
        raise SceneError(f"--shard {text!r}: need 0 <= i < n")
    return a, b


def parse_split(text: str) -> tuple[float, float, float]:
    try:
        parts = tuple(float(x) for x in text.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 3 or not all(math.isfinite(x) for x in parts) or min(parts) < 0 or sum(parts) <= 0:
        raise SceneError(f"--split {text!r}: expected three non-negative fractions train,val,test, e.g. 0.8,0.1,0.1")
    return parts  # type: ignore[return-value]
