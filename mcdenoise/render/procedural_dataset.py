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
import math
import re
import time
from pathlib import Path
from typing import Any, Callable, Collection

from mcdenoise.errors import SceneError
from mcdenoise.io.safety import DEFAULT_MAX_BYTES, WriterLock, check_space

# Re-exported: the names this module had before it was split (one concern per file).
from mcdenoise.render.dataset_config import (  # noqa: F401
    CONFIG_FILE,
    GENERATOR,
    RENDER_VARIANTS,
    DatasetConfig,
    _read_config,
    _write_config,
    image_paths,
    images_variant,
    recorded_variant,
    scene_name,
    shard_indices,
    split_indices,
)
from mcdenoise.render.dataset_folder import _is_finished, clean_partial, finished_paths, rebuild_manifest  # noqa: F401
from mcdenoise.render.procedural_image import VIEW_ATTEMPTS, render_procedural_image  # noqa: F401

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
    splits: Collection[str] | None = None,
) -> dict[str, Any]:
    """Render the missing images of shard ``shard/shards`` into ``root``; returns a summary.

    ``splits`` (e.g. ``{"val"}``) renders only the scenes the recipe's split puts there: the
    same pixels as a full run's, since scene ``i`` depends only on (seed, i), so a new machine
    gets a campaign's held-out images back without rendering its training scenes. A later
    run without it renders the rest. Rebuilds the manifest after each image and at the end
    (from a fresh scan, which picks up folders other shards wrote meanwhile).
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
    if splits is not None:
        n = len(indices)
        indices = split_indices(cfg, indices, splits)
        if log is not None:
            log(f"{root}: only split(s) {','.join(sorted(splits))}: {len(indices)} of {n} scene(s)")
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
