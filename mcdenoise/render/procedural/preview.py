"""The rejection check: a cheap render of a drawn scene, its luminance and object coverage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mcdenoise.color import luminance
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.procedural.loading import load_procedural
from mcdenoise.render.procedural.scene import ProceduralScene

__all__ = ["PREVIEW_SIZE", "PREVIEW_SPP", "PreviewStats", "image_stats", "object_mask", "preview_stats"]


#: Preview size (pixels on the long side) and samples per pixel of the standalone rejection check
#: (the dataset previews at the input image's own size and spp instead).
PREVIEW_SIZE, PREVIEW_SPP = 32, 8


@dataclass
class PreviewStats:
    """What the rejection check measured on a tiny render (luminances are linear)."""

    mean: float
    median: float
    black_fraction: float
    object_fraction: float
    finite: bool

    def problem(self) -> str | None:
        """Why the scene is rejected, or None when it is fine."""
        if not self.finite:
            return "non-finite pixels"
        if self.mean <= 1e-8 or self.median <= 1e-12:
            return "renders black"
        if self.black_fraction > 0.5:
            return f"{self.black_fraction:.0%} of the image is black"
        if self.object_fraction < 0.08:
            return f"objects cover only {self.object_fraction:.0%} of the image"
        return None


def preview_stats(
    ps: ProceduralScene,
    *,
    size: int = PREVIEW_SIZE,
    spp: int = PREVIEW_SPP,
    seed: int = 0,
    scene: Any = None,
    settings: Any = None,
    record_position: bool = False,
    block: int = 1,
    stack_camera: np.ndarray | None = None,
) -> PreviewStats:
    """Render ``ps`` cheaply with our integrator and measure luminance statistics, plus object
    coverage from one ray per pixel centre.

    Standalone (``scene``/``settings`` None): the dict is loaded with its film shrunk to ``size``
    pixels on the long side and rendered at ``spp``. The dataset instead passes its loaded
    ``scene`` and the input image's own :class:`~mcdenoise.render.api.RenderSettings` (size, spp,
    motion), so that the preview compiles exactly the kernel the input then reuses: the check
    costs one input-sized trace, not a compilation of its own. ``seed`` replaces the settings'
    seed (the preview's noise is independent of the input's). ``block`` > 1 measures the luminance
    statistics on the means of ``block`` x ``block`` pixel blocks (a low-spp check; the image's
    last rows and columns that fill no block are left out); coverage stays per pixel.
    ``stack_camera`` (the sensor's current pose, 4x4) renders through a view stack of that one
    camera (:mod:`mcdenoise.render.view_stack`), so that the check compiles the kernel the
    stacked inputs then reuse (generator 4's views).
    """
    from dataclasses import replace

    from mcdenoise.render.api import RenderSettings, render_samples

    mi = mitsuba()
    if settings is None:
        film = ps.scene["sensor"]["film"]
        w, h = film["width"], film["height"]
        k = size / max(w, h)
        settings = RenderSettings(spp=spp, ref_spp=0, width=max(1, round(w * k)), height=max(1, round(h * k)), max_depth=6)
    settings = replace(settings, seed=int(seed))
    if scene is None:
        scene = load_procedural(ps, settings.width, settings.height)
    if stack_camera is not None:
        from mcdenoise.render.view_stack import render_view_stack

        # The stack keeps every input channel (the kept outputs are part of the kernel, which
        # the inputs then reuse); only the radiance is read.
        arrays = render_view_stack(scene, settings, [stack_camera], stack_camera, seed=settings.seed)[0]
    else:
        arrays, _ = render_samples(scene, settings, record_position=record_position)
    img = arrays["radiance"].mean(axis=0, dtype=np.float64).transpose(1, 2, 0)
    del arrays
    return image_stats(img, _object_mask(mi, scene, settings.width, settings.height), block)


def image_stats(img: np.ndarray, is_obj: np.ndarray, block: int = 1) -> PreviewStats:
    """The check's statistics of a rendered image ``img`` (H, W, 3) with its object mask (H, W),
    luminance measured on ``block`` x ``block`` pixel blocks (see :func:`preview_stats`)."""
    lum = luminance(img)
    if block > 1:
        hb, wb = lum.shape[0] // block, lum.shape[1] // block
        if hb and wb:
            lum = lum[: hb * block, : wb * block].reshape(hb, block, wb, block).mean(axis=(1, 3))
    finite = bool(np.isfinite(img).all())
    mean = float(lum.mean()) if finite else 0.0
    return PreviewStats(
        mean=mean,
        median=float(np.median(lum)) if finite else 0.0,
        black_fraction=float((lum <= 1e-4 * max(mean, 1e-30)).mean()),
        object_fraction=float(is_obj.mean()),
        finite=finite,
    )


def object_mask(loaded: Any, width: int, height: int) -> np.ndarray:
    """(height, width) bool: the pixel centre's ray first hits a random object or furniture, seen
    from the loaded scene's sensor as posed now."""
    return _object_mask(mitsuba(), loaded, width, height)


def _object_mask(mi: Any, loaded: Any, width: int, height: int) -> np.ndarray:
    """(height, width) bool: the ray through the pixel centre first hits a random object or
    furniture (shapes compared by their Dr.Jit registry ids, one vectorised ray cast).

    A preliminary intersection is enough to know the shape, and its kernel is tiny (a full
    ``ray_intersect`` evaluates textures and frames of every material).
    """
    import drjit as dr

    sensor = loaded.sensors()[0]
    y, x = np.mgrid[0:height, 0:width]
    film_pos = mi.Point2f(((x.ravel() + 0.5) / width).astype(np.float32), ((y.ravel() + 0.5) / height).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, film_pos, mi.Point2f(0.5, 0.5))
    hit_ids = np.array(dr.reinterpret_array(mi.UInt32, loaded.ray_intersect_preliminary(ray).shape))
    obj_ids = [
        int(np.array(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s)))[0])
        for s in loaded.shapes()
        if s.id().startswith(("object_", "furniture_"))
    ]
    return np.isin(hit_ids, obj_ids).reshape(height, width)
