"""Render one image folder of the data format: per-sample data streamed to disk, the reference,
meta.json; written through :class:`mcdenoise.data.writer.SampleWriter` (atomic, checked)."""

from __future__ import annotations

import os
import sys
import warnings
import time as _time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from mcdenoise.errors import OutputExistsError, SceneError
from mcdenoise.io.safety import DEFAULT_MAX_BYTES, WriterLock, check_output_path
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.integrator import INTEGRATOR_NAME
from mcdenoise.render.reference import render_reference
from mcdenoise.render.samples import iter_sample_chunks
from mcdenoise.render.scene_loading import scene_features
from mcdenoise.render.settings import RenderSettings

__all__ = ["render_image"]


def _renderer_string() -> str:
    mi = mitsuba()
    from mcdenoise import __version__

    return f"mitsuba {mi.__version__} ({mi.variant()}) / mcdenoise {__version__}"


def render_image(
    scene: Any,
    out_dir: str | os.PathLike,
    settings: RenderSettings,
    *,
    scene_name: str = "",
    extra_meta: dict | None = None,
    camera_to_world: np.ndarray | None = None,
    record_position: bool = False,
    overwrite: bool = False,
    progress: bool = False,
    extra_noisy: dict[str, np.ndarray] | None = None,
    nonfinite: str = "sanitize",
    max_bytes: int | None = DEFAULT_MAX_BYTES,
    reference: tuple[dict[str, np.ndarray], int] | None = None,
    samples: dict[str, np.ndarray] | None = None,
) -> Path:
    """Render one image folder (per-sample data, noisy.exr, reference.exr, meta.json), atomically.

    ``reference`` = (layers ``name -> (C, H, W)``, its spp) stores a reference made elsewhere
    (e.g. the validation scenes' 8192-spp references) instead of rendering one; then
    ``settings.ref_spp`` must be 0. ``samples`` (name -> (S, C, H, W) float32, every channel of
    ``settings.sample_channels()``) stores per-sample data rendered elsewhere (a view stack,
    :mod:`mcdenoise.render.view_stack`) instead of rendering it; the reference is still rendered here.

    The per-sample data is streamed to disk band by band, so memory stays bounded at any size.
    ``record_position`` adds a per-pixel ``position`` buffer (mean over samples) to noisy.exr;
    ``extra_noisy`` adds caller-made per-pixel layers ``(C, H, W)`` (e.g. ``motion``).
    ``nonfinite`` (``sanitize`` | ``error``) applies :func:`mcdenoise.data.finite.sanitize_nonfinite`
    to every sample and layer; replacements are counted in meta.json (``extra.nonfinite_replaced``)
    and warned about. Only one writer renders into ``out_dir`` at a time (a sibling lock file), an
    existing folder is replaced only when mcdenoise wrote it, and the size is checked against the
    free space and ``max_bytes`` before anything is allocated.
    """
    out = Path(out_dir)
    try:
        check_output_path(out, overwrite=overwrite)
    except OutputExistsError as e:
        raise SceneError(str(e)) from None  # render_image's documented error for an existing folder
    lock = WriterLock(out.with_name(f".{out.name}.lock"), f"render {out.name}").acquire()
    try:
        return _render_locked(scene, out, settings, scene_name=scene_name, extra_meta=extra_meta,
                              camera_to_world=camera_to_world, record_position=record_position, overwrite=overwrite,
                              progress=progress, extra_noisy=extra_noisy, nonfinite=nonfinite, max_bytes=max_bytes,
                              given_reference=reference, given_samples=samples)
    finally:
        lock.release()


def _render_locked(scene: Any, out: Path, settings: RenderSettings, *, scene_name: str, extra_meta: dict | None,
                   camera_to_world: np.ndarray | None, record_position: bool, overwrite: bool, progress: bool,
                   extra_noisy: dict[str, np.ndarray] | None, nonfinite: str, max_bytes: int | None,
                   given_reference: tuple[dict[str, np.ndarray], int] | None = None,
                   given_samples: dict[str, np.ndarray] | None = None) -> Path:
    import drjit as dr

    from mcdenoise.data import format as fmt

    t0 = _time.perf_counter()
    channels = list(settings.sample_channels())
    feats = scene_features(scene)
    extra: dict[str, Any] = {
        "max_depth": settings.max_depth,
        "rr_depth": settings.rr_depth,
        "integrator": INTEGRATOR_NAME,
        "filter": "box",
        "time_slices": bool(settings.object_motion),
    }
    if settings.object_motion:
        extra["object_motion"] = {k: list(map(float, v)) for k, v in settings.object_motion.items()}
    if settings.camera_to_world_end is not None:
        extra["camera_to_world_end"] = np.asarray(settings.camera_to_world_end, dtype=float).tolist()
    if camera_to_world is not None:
        extra["camera_to_world"] = np.asarray(camera_to_world, dtype=float).tolist()
    extra.update(extra_meta or {})
    meta = fmt.ImageMeta(
        width=settings.width,
        height=settings.height,
        spp=settings.spp,
        channels=channels,
        scene=scene_name,
        seed=settings.seed,
        renderer=_renderer_string(),
        scene_features=feats,
        reference_spp=settings.ref_spp if settings.ref_spp > 0 else (given_reference[1] if given_reference else None),
        extra=extra,
    )
    writer = fmt.SampleWriter(out, meta, overwrite=overwrite, nonfinite=nonfinite, max_bytes=max_bytes)
    total = settings.width * settings.height * (settings.spp + max(0, settings.ref_spp))
    bar = tqdm(total=total, unit="sample", unit_scale=True, desc=f"render {out.name}", disable=not progress,
               leave=False, file=sys.stderr)
    try:
        pos_sum = np.zeros((3, settings.height, settings.width), dtype=np.float64) if record_position else None
        if given_samples is not None:
            if record_position:
                raise ValueError("render_image: record_position needs the samples rendered here")
            want = (settings.spp, settings.height, settings.width)
            for name in channels:
                got = given_samples[name].shape if name in given_samples else None
                if got is None or (got[0], got[2], got[3]) != want:
                    raise ValueError(f"render_image: given samples {name!r} are {got}, expected (spp, C, H, W) = {want}")
            chunks: Any = [(slice(0, settings.spp), slice(0, settings.height), given_samples)]
        else:
            chunks = iter_sample_chunks(scene, settings, camera_to_world=camera_to_world, record_position=record_position)
        for samples, rows, chunk in chunks:
            if pos_sum is not None:
                pos_sum[:, rows] += chunk.pop("position").sum(axis=0, dtype=np.float64)
            for name in channels:
                writer.write(name, chunk[name], samples=samples, rows=rows)
            bar.update((samples.stop - samples.start) * (rows.stop - rows.start) * settings.width)
        # The per-sample arrays live in Dr.Jit memory (see _sample_major); once written, their
        # blocks idle in Dr.Jit's allocation cache at sizes the reference cannot reuse (+0.35 GiB
        # peak at 1024x1024, 64 spp): drop the last band's and hand them back before it starts.
        chunk = {}
        dr.flush_malloc_cache()
        t1 = _time.perf_counter()
        reference = None
        if given_reference is not None:
            if settings.ref_spp > 0:
                raise ValueError("render_image: a given reference needs settings.ref_spp == 0")
            reference = {k: np.asarray(v, np.float32) for k, v in given_reference[0].items()}
            for k, v in reference.items():
                if v.shape[-2:] != (settings.height, settings.width):
                    raise ValueError(f"render_image: given reference {k!r} is {v.shape}, the image {settings.height}x{settings.width}")
        elif settings.ref_spp > 0:
            reference = render_reference(scene, settings, camera_to_world=camera_to_world, progress=bar.update)
        t2 = _time.perf_counter()
        meta.extra["render_seconds"] = {"samples": round(t1 - t0, 3), "reference": round(t2 - t1, 3)}
        per_pixel = dict(extra_noisy or {})
        if pos_sum is not None:
            per_pixel["position"] = (pos_sum / settings.spp).astype(np.float32)
    except BaseException:
        writer.abort()
        raise
    finally:
        bar.close()
    path = writer.finish(reference=reference, extra_noisy=per_pixel or None)
    if writer.nonfinite:
        warnings.warn(f"{path}: {writer.nonfinite} non-finite sample value(s) (NaN/Inf) replaced by 0 "
                      "(--nonfinite error refuses them instead)", stacklevel=2)
    return path
