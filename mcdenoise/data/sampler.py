"""Torch-free crop sampler: random crops (and random spp subsets) from a set of image folders.

Kept apart from the reader (``format.py``) and from tensor conversion (the training code): this
only decides *which* bytes to read. Item ``i`` is a pure function of ``(seed, i)``, so data-loader
workers need no shared state and a run is reproducible.

Crop placement (``sampling``):

* ``"uniform"``: every window of the image equally likely.
* ``"importance"``: KPCN Sec. 5.1. Candidate windows are thrown uniformly (dart throwing) and
  accepted with probability ``min(1, score / s90)`` (``s90``: the image's 90th percentile of
  window scores, so a single firefly does not make every other window rare), where a window's score is the mean over it of
  :func:`importance_map` (relative colour variance: noise; normal variance and gradient: geometry;
  gradient of the log reference: texture and detail). After ``accept_after`` rejections the next
  candidate is accepted whatever its score, so smooth regions are still shown now and then (the
  paper's balance between easy and hard cases).

Targets (``target``):

* ``"reference"``: the converged ``reference.exr``.
* ``"noisy"`` (Noise2Noise): the mean over the *held-out* samples of the same render, i.e. every
  stored sample that the input did not use. Input and target samples are disjoint, so their noise
  is independent and an L2-type loss stays unbiased (its minimiser is the clean image).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mcdenoise.color import luminance
from mcdenoise.data.channels import base_name, is_variance_name
from mcdenoise.data.format import ImageFolder, pixel_stats
from mcdenoise.data.oidn_input import oidn_for, split_oidn

__all__ = ["Crop", "CropSampler", "importance_map", "window_scores", "SAMPLINGS", "TARGETS"]

SAMPLINGS = ("uniform", "importance")
TARGETS = ("reference", "noisy")
#: Windows scoring above this quantile of an image's window scores are always accepted.
ACCEPT_QUANTILE = 0.9


@dataclass
class Crop:
    """One training example.

    Attributes:
        inputs: channel name -> ``(s, C, h, w)`` (kind ``"samples"``) or ``(C, h, w)`` (``"pixels"``;
            ``*_variance`` names are variances of the mean), float32.
        reference: reference channel name -> ``(C, h, w)`` float32 (with ``target="noisy"``: the
            mean of the held-out samples).
        scene_features: ``(len(SCENE_FEATURES),)`` float32.
        path: the image folder; origin: ``(y0, x0)``; samples: sample indices used (None = all, as
            stored in noisy.exr); target_samples: the held-out indices of a noisy target (else None).
    """

    inputs: dict[str, np.ndarray]
    reference: dict[str, np.ndarray]
    scene_features: np.ndarray
    path: Path
    origin: tuple[int, int]
    samples: list[int] | None = field(default=None)
    target_samples: list[int] | None = field(default=None)


def _grad_mag(x: np.ndarray) -> np.ndarray:
    """``(C, H, W)`` -> ``(H, W)``: sum over channels of |forward difference| in x plus in y."""
    g = np.zeros(x.shape[1:], np.float64)
    g[:, :-1] += np.abs(np.diff(x, axis=2)).sum(axis=0)
    g[:-1, :] += np.abs(np.diff(x, axis=1)).sum(axis=0)
    return g


def _unit_mean(x: np.ndarray) -> np.ndarray:
    # Each term is scaled to mean 1 over the image, so no term dominates by its units.
    m = float(x.mean())
    return x / m if m > 0 else np.zeros_like(x)


def _local_variance(x: np.ndarray) -> np.ndarray:
    """Variance of ``x`` (H, W) over each pixel's 3x3 neighbourhood (edge-replicated), float64."""
    p = np.pad(x, 1, mode="edge")
    h, w = x.shape
    win = np.stack([p[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)])
    return win.var(axis=0)


def importance_map(noisy: dict[str, np.ndarray], reference: dict[str, np.ndarray] | None) -> np.ndarray:
    """Per-pixel crop importance ``(H, W)`` float64, >= 0 (KPCN Sec. 5.1).

    Sum of three terms, each normalised to mean 1 over the image:

    * noise: luminance variance of the mean of ``radiance`` over ``(mean luminance^2 + 1e-2)``
      (relative, so bright regions do not win by brightness alone);
    * geometry: mean ``normal_variance`` plus the gradient magnitude of ``normal`` (when stored);
    * detail: gradient magnitude of ``log(1 + reference radiance)``; without a reference, of the
      noisy ``albedo`` (texture), which carries little Monte Carlo noise.

    Args:
        noisy: per-pixel buffers ``(C, H, W)`` as in ``noisy.exr``; needs ``radiance``, and uses
            ``radiance_variance`` where there is one (else the 3x3 variance of the luminance).
        reference: reference buffers or None.
    """
    rad = noisy["radiance"].astype(np.float64)
    lum = luminance(rad, 0)
    if "radiance_variance" in noisy:
        var = luminance(noisy["radiance_variance"].astype(np.float64), 0)
    else:  # pixel-only input: the luminance's variance over its 3x3 neighbourhood stands in
        var = _local_variance(lum)
    score = _unit_mean(var / (lum * lum + 1e-2))
    if "normal" in noisy:
        geo = _grad_mag(noisy["normal"].astype(np.float64))
        if "normal_variance" in noisy:
            geo = geo + noisy["normal_variance"].astype(np.float64).mean(axis=0)
        score = score + _unit_mean(geo)
    if reference is not None and "radiance" in reference:
        score = score + _unit_mean(_grad_mag(np.log1p(np.maximum(reference["radiance"].astype(np.float64), 0))))
    elif "albedo" in noisy:
        score = score + _unit_mean(_grad_mag(noisy["albedo"].astype(np.float64)))
    return np.nan_to_num(score, nan=0.0, posinf=0.0)


def window_scores(pixel_score: np.ndarray, crop: int) -> np.ndarray:
    """Mean of ``pixel_score (H, W)`` over every ``crop x crop`` window -> ``(H-crop+1, W-crop+1)``,
    indexed by the window's top-left corner (summed-area table, float64)."""
    s = np.zeros((pixel_score.shape[0] + 1, pixel_score.shape[1] + 1), np.float64)
    s[1:, 1:] = pixel_score.cumsum(axis=0).cumsum(axis=1)
    c = crop
    return (s[c:, c:] - s[:-c, c:] - s[c:, :-c] + s[:-c, :-c]) / (c * c)


class CropSampler:
    """Random ``crop x crop`` windows from ``images``.

    Args:
        images: image folders (e.g. ``Dataset(root).images("train")``); each needs a reference
            unless ``target="noisy"``.
        crop: window edge in pixels.
        channels: input channel names; for ``kind="pixels"`` they may include ``*_variance``.
        kind: ``"samples"`` (read per-sample data) or ``"pixels"`` (per-pixel means/variances).
        spp_range: ``(lo, hi)``: draw the sample count uniformly in ``lo..hi`` and a random subset
            of that many samples per item (SBMC trains with 2..8). For ``"pixels"`` the means and
            variances are then recomputed from that subset (needs per-sample data). None = all
            samples / the stored noisy.exr (with ``target="noisy"``: half the samples).
        reference: reference channel names to return (the target's channels).
        seed: base seed; item ``i`` uses ``numpy.random.default_rng([seed, i])``.
        length: nominal ``len()`` (items are drawn with replacement; any index is valid).
        max_cached: how many images' per-pixel buffers to keep in memory (EXRs are read whole).
        sampling: ``"uniform"`` or ``"importance"`` (see the module docstring).
        accept_after: importance sampling accepts the candidate after this many rejections.
        target: ``"reference"`` or ``"noisy"`` (held-out samples; see the module docstring).
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
        sampling: str = "uniform",
        accept_after: int = 8,
        target: str = "reference",
    ) -> None:
        if kind not in ("samples", "pixels"):
            raise ValueError(f"kind must be 'samples' or 'pixels', got {kind!r}")
        if sampling not in SAMPLINGS:
            raise ValueError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
        if target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
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
        self.sampling, self.accept_after, self.target = sampling, accept_after, target
        self._cache: OrderedDict[Path, ImageFolder] = OrderedDict()
        self._scores: dict[Path, np.ndarray] = {}
        self._caps: dict[Path, float] = {}
        noisy_target = target == "noisy"
        # A pixel-only image (no samples.bin: a converted Cycles or pbrt render) gives a pixel
        # model its stored noisy.exr at its own spp, whatever ``spp_range`` says.
        needs_samples = kind == "samples" or noisy_target
        for im in self.images:
            m = im.meta
            if m.height < crop or m.width < crop:
                raise ValueError(f"{im.path}: {m.height}x{m.width} is smaller than the {crop}x{crop} crop")
            if not noisy_target and not im.has_reference:
                raise ValueError(f"{im.path}: no reference.exr to train against")
            if needs_samples and im.samples is None:
                raise ValueError(f"{im.path}: no per-sample data (needed for kind={kind!r}, spp_range={spp_range}, target={target!r})")
            if (spp_range is not None and im.samples is not None
                    and not 1 <= spp_range[0] <= spp_range[1] <= m.spp):
                raise ValueError(f"{im.path}: spp_range {spp_range} outside 1..{m.spp}")
            if noisy_target:
                hi = spp_range[1] if spp_range is not None else m.spp // 2
                if hi < 1 or m.spp - hi < 1:
                    raise ValueError(f"{im.path}: target='noisy' needs held-out samples: {m.spp} spp stored, "
                                     f"up to {hi} used as input")
                missing = [c for c in self.reference if c not in m.channels]
                if missing:
                    raise ValueError(f"{im.path}: target='noisy' averages per-sample {missing}, which are not stored")
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

    def window_scores(self, im: ImageFolder) -> np.ndarray:
        """Importance of every crop window of ``im`` ``(H-crop+1, W-crop+1)``, computed once per image."""
        sc = self._scores.get(im.path)
        if sc is None:
            px = self._pixels(im)
            # Every layer there is: a pixel-only image (a converted Cycles file) may have no variances.
            noisy = {n: a for n, a in px.read_noisy().items()
                     if n in ("radiance", "radiance_variance", "normal", "normal_variance", "albedo")}
            ref = px.read_reference(["radiance"]) if im.has_reference else None
            sc = window_scores(importance_map(noisy, ref), self.crop).astype(np.float32)
            self._scores[im.path] = sc
        return sc

    def _origin(self, rng: np.random.Generator, im: ImageFolder) -> tuple[int, int]:
        m = im.meta
        ny, nx = m.height - self.crop + 1, m.width - self.crop + 1
        if self.sampling == "uniform":
            return int(rng.integers(ny)), int(rng.integers(nx))
        sc = self.window_scores(im)
        # The acceptance scale is a high quantile, not the maximum: one firefly window would
        # otherwise make every other candidate rare and the auto-accept turn this into uniform.
        top = self._caps.get(im.path)
        if top is None:
            top = self._caps[im.path] = float(np.quantile(sc, ACCEPT_QUANTILE))
        for _ in range(self.accept_after):
            y0, x0 = int(rng.integers(ny)), int(rng.integers(nx))
            u = float(rng.random())
            if top <= 0 or u * top < sc[y0, x0]:
                return y0, x0
        return int(rng.integers(ny)), int(rng.integers(nx))

    def __getitem__(self, i: int) -> Crop:
        return self.draw(np.random.default_rng([self.seed, int(i)]))

    def draw(self, rng: np.random.Generator, *, spp: int | None = None) -> Crop:
        """One crop drawn with ``rng`` (image, window, then samples).

        ``spp`` fixes the number of input samples (needs per-sample data) instead of drawing it
        from ``spp_range``: the training loop draws one count per batch so that every row of a
        sample model's batch has the same ``S``. A pixel-only image ignores both: its input is its
        stored noisy.exr, at the spp it was rendered with.
        """
        im = self.images[int(rng.integers(len(self.images)))]
        m = im.meta
        y0, x0 = self._origin(rng, im)
        box = (y0, x0, self.crop, self.crop)
        idx: list[int] | None = None
        held: list[int] | None = None
        n = None  # a pixel-only image: its stored noisy.exr
        if im.samples is not None:
            n = spp
            if n is None and self.spp_range is not None:
                n = int(rng.integers(self.spp_range[0], self.spp_range[1] + 1))
        if self.target == "noisy":
            n = m.spp // 2 if n is None else n
            if not 1 <= n < m.spp:
                raise ValueError(f"{im.path}: {n} input samples leave none of {m.spp} for the noisy target")
            perm = rng.permutation(m.spp)
            idx, held = sorted(int(v) for v in perm[:n]), sorted(int(v) for v in perm[n:])
        elif n is not None:
            if not 1 <= n <= m.spp:
                raise ValueError(f"{im.path}: spp {n} outside 1..{m.spp}")
            idx = sorted(int(v) for v in rng.choice(m.spp, size=n, replace=False))
        channels, want_oidn = split_oidn(self.channels)
        if want_oidn:
            # OIDN's output is cached per image and sample count for the first n samples (issue 20):
            # the input must be exactly those, the held-out target the others.
            n_in = len(idx) if idx is not None else m.spp
            idx = list(range(n_in)) if idx is not None else None
            held = list(range(n_in, m.spp)) if held is not None else None
        px = self._pixels(im)
        if self.kind == "samples":
            inputs = im.samples.read(self.channels, crop=box, samples=idx)
        elif idx is None:
            inputs = px.read_noisy(channels, crop=box)
        else:
            bases = list(dict.fromkeys(base_name(c) for c in channels))
            smp = im.samples.read(bases, crop=box, samples=idx)
            stats = {}
            for b in bases:
                stats[b], stats[b + "_variance"] = pixel_stats(smp[b])
            inputs = {c: stats[c] for c in channels}
        if want_oidn:
            y, x, h, w = box
            for ch in want_oidn:
                full = oidn_for(im, len(idx) if idx is not None else None, channel=ch)
                inputs[ch] = np.ascontiguousarray(full[:, y : y + h, x : x + w])
        if held is not None:
            tgt = im.samples.read(self.reference, crop=box, samples=held)
            ref = {k: v.mean(axis=0, dtype=np.float64).astype(np.float32) for k, v in tgt.items()}
        else:
            ref = px.read_reference(self.reference, crop=box)
        return Crop(inputs, ref, m.scene_feature_vector(), im.path, (y0, x0), idx, held)
