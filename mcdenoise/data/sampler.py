"""Torch-free crop sampler: random crops (and random spp subsets) from a set of image folders.

Kept apart from the reader (``format.py``) and from tensor conversion (the training code): this
only decides *which* bytes to read. Item ``i`` is a pure function of ``(seed, i)``, so data-loader
workers need no shared state and a run is reproducible.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcdenoise.data.channels import base_name, is_variance_name
from mcdenoise.data.format import ImageFolder, pixel_stats

__all__ = ["Crop", "CropSampler"]


@dataclass
class Crop:
    """One training example.

    Attributes:
        inputs: channel name -> ``(s, C, h, w)`` (kind ``"samples"``) or ``(C, h, w)`` (``"pixels"``;
            ``*_variance`` names are variances of the mean), float32.
        reference: reference channel name -> ``(C, h, w)`` float32.
        scene_features: ``(len(SCENE_FEATURES),)`` float32.
        path: the image folder; origin: ``(y0, x0)``; samples: sample indices used (None = all, as
            stored in noisy.exr).
    """

    inputs: dict[str, np.ndarray]
    reference: dict[str, np.ndarray]
    scene_features: np.ndarray
    path: Path
    origin: tuple[int, int]
    samples: list[int] | None = field(default=None)


class CropSampler:
    """Random ``crop x crop`` windows from ``images``.

    Args:
        images: image folders (e.g. ``Dataset(root).images("train")``); each needs a reference.
        crop: window edge in pixels.
        channels: input channel names; for ``kind="pixels"`` they may include ``*_variance``.
        kind: ``"samples"`` (read per-sample data) or ``"pixels"`` (per-pixel means/variances).
        spp_range: ``(lo, hi)``: draw the sample count uniformly in ``lo..hi`` and a random subset
            of that many samples per item (SBMC trains with 2..8). For ``"pixels"`` the means and
            variances are then recomputed from that subset (needs per-sample data). None = all
            samples / the stored noisy.exr.
        reference: reference channel names to return.
        seed: base seed; item ``i`` uses ``numpy.random.default_rng([seed, i])``.
        length: nominal ``len()`` (items are drawn with replacement; any index is valid).
        max_cached: how many images' per-pixel buffers to keep in memory (EXRs are read whole).
    """

    def __init__(
        self,
        images: Sequence[ImageFolder],
        *,
        crop: int,
        channels: Sequence[str],
        kind: str = "samples",
        spp_range: tuple[int, int] | None = None,
        reference: Sequence[str] = ("radiance",),
        seed: int = 0,
        length: int = 1000,
        max_cached: int = 4,
    ) -> None:
        if kind not in ("samples", "pixels"):
            raise ValueError(f"kind must be 'samples' or 'pixels', got {kind!r}")
        if not images:
            raise ValueError("CropSampler: no images")
        if crop < 1:
            raise ValueError("crop must be >= 1")
        self.images = list(images)
        self.crop, self.kind, self.seed, self.length = crop, kind, seed, length
        self.channels = list(channels)
        self.reference = list(reference)
        self.spp_range = spp_range
        self.max_cached = max_cached
        self._cache: OrderedDict[Path, ImageFolder] = OrderedDict()
        needs_samples = kind == "samples" or spp_range is not None
        for im in self.images:
            m = im.meta
            if m.height < crop or m.width < crop:
                raise ValueError(f"{im.path}: {m.height}x{m.width} is smaller than the {crop}x{crop} crop")
            if not im.has_reference:
                raise ValueError(f"{im.path}: no reference.exr to train against")
            if needs_samples and im.samples is None:
                raise ValueError(f"{im.path}: no per-sample data (needed for kind={kind!r}, spp_range={spp_range})")
            if spp_range is not None and not 1 <= spp_range[0] <= spp_range[1] <= m.spp:
                raise ValueError(f"{im.path}: spp_range {spp_range} outside 1..{m.spp}")
        if kind == "samples" and any(is_variance_name(c) for c in self.channels):
            raise ValueError("kind='samples' reads per-sample channels; variances exist only per pixel")

    def __len__(self) -> int:
        return self.length

    def _pixels(self, im: ImageFolder) -> ImageFolder:
        """A caching twin of ``im`` (LRU of ``max_cached``): the EXRs are read once, cropped many times."""
        cached = self._cache.get(im.path)
        if cached is None:
            cached = ImageFolder(im.path, cache=True)
            self._cache[im.path] = cached
            while len(self._cache) > self.max_cached:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(im.path)
        return cached

    def __getitem__(self, i: int) -> Crop:
        rng = np.random.default_rng([self.seed, int(i)])
        im = self.images[int(rng.integers(len(self.images)))]
        m = im.meta
        y0 = int(rng.integers(m.height - self.crop + 1))
        x0 = int(rng.integers(m.width - self.crop + 1))
        box = (y0, x0, self.crop, self.crop)
        idx: list[int] | None = None
        if self.spp_range is not None:
            n = int(rng.integers(self.spp_range[0], self.spp_range[1] + 1))
            idx = sorted(int(v) for v in rng.choice(m.spp, size=n, replace=False))
        px = self._pixels(im)
        if self.kind == "samples":
            inputs = im.samples.read(self.channels, crop=box, samples=idx)
        elif idx is None:
            inputs = px.read_noisy(self.channels, crop=box)
        else:
            bases = list(dict.fromkeys(base_name(c) for c in self.channels))
            smp = im.samples.read(bases, crop=box, samples=idx)
            stats = {}
            for b in bases:
                stats[b], stats[b + "_variance"] = pixel_stats(smp[b])
            inputs = {c: stats[c] for c in self.channels}
        ref = px.read_reference(self.reference, crop=box)
        return Crop(inputs, ref, m.scene_feature_vector(), im.path, (y0, x0), idx)
