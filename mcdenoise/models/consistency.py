"""Keep a denoised pixel inside what its own samples allow (issue 19: never worse than the input).

A per-sample model sees each pixel's ``S`` samples, so it knows how far the pixel's mean can be
from the truth: about ``k`` standard errors. A network that moves a pixel further than that has
filtered something the samples contradict: light bled over an edge into a dark pixel, a
reflection's detail blurred away. Those are the pixels that made the per-sample models worse than
the noisy input at 16 spp, where the standard errors are small (docs/models/consistency.md).

The clamp, per pixel and colour channel::

    v      = unbiased sample variance of the pixel's S samples
    v_bar  = mean of v over the WINDOW x WINDOW box around it
    s^2    = ((S - 1) v + PRIOR v_bar) / (S - 1 + PRIOR)         (shrunk toward the neighbourhood)
    out    = clamp(out, mean - k sqrt(s^2 / S), mean + k sqrt(s^2 / S))

The shrinkage is why this works at 4 spp too: a pixel whose few samples agree (all four missed
the light) has ``v = 0`` but is not noise-free; its neighbourhood's variance, weighted as ``PRIOR``
samples, says how far it may move. A firefly's own variance is large, so its bound is loose and
the network removes it as before. With ``S = 1`` there is no variance: the output passes as it is.

Plain PyTorch (it is its own reference). ``k`` is ``consistency`` in the SBMC, layer, WSKP and KPCN
configs, chosen after training on our own held-out images (``scripts/consistency_probe.py``). The
sample models clamp in their forward (:func:`consistency_clamp`); a pixel model sees no samples,
so ``denoise`` and ``eval`` clamp its output from the input's per-pixel statistics
(:func:`pixel_consistency_clamp`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["ConsistencyOptions", "PRIOR", "WINDOW", "MEDIAN_BAND", "acts_at", "bounds", "sample_bounds",
           "consistency_clamp", "pixel_consistency_clamp", "check_consistency"]


@dataclass
class ConsistencyOptions:
    """How the clamp is applied, beside ``consistency`` (k) itself: a base of the SBMC, layer, WSKP
    and KPCN configurations. Set after training, with ``consistency``
    (``scripts/reconfigure_weights.py --set``), chosen on held-out images."""

    consistency_min_spp: int = 2
    """The fewest samples per pixel at which ``consistency`` acts (2: whenever there is a variance).
    Why a higher count: at 4 spp a pixel's variance has 3 degrees of freedom and the clamp moved
    the layer models' held-out mean PSNR by a few thousandths of a dB either way, while at 8-16 spp
    it is what lifts it (campaigns 19-23, docs/models/consistency.md). Set after training, with
    ``consistency``."""

    consistency_box: str = "mean"
    """The neighbourhood variance the clamp shrinks a pixel's own toward: the ``"mean"`` or the
    ``"median"`` over its 5x5 box (:func:`mcdenoise.models.consistency.bounds`). Set after
    training, with ``consistency`` (campaign 23)."""


#: Weight of the neighbourhood's variance, in samples (chosen on held-out images: 0 left pixels
#: whose few samples agree stuck at their mean, and cost 2.4-5.4 dB of PSNR at 4-8 spp:
#: ``scripts/consistency_probe.py ... --prior 0``).
PRIOR = 2.0
#: Side of the box the neighbourhood's variance is averaged over.
WINDOW = 5


#: Rows of the image whose box medians are taken at once (the unfolded windows hold WINDOW^2 copies).
MEDIAN_BAND = 64


def _box_median(x: torch.Tensor) -> torch.Tensor:
    """``(N, 1, H, W)`` -> the median over each pixel's WINDOW x WINDOW box (replicate-padded),
    a band of rows at a time so that 1080p does not hold 25 copies of the image."""
    n, _, h, w = x.shape
    pad = WINDOW // 2
    xp = F.pad(x, [pad] * 4, mode="replicate")
    out = []
    for y0 in range(0, h, MEDIAN_BAND):
        y1 = min(h, y0 + MEDIAN_BAND)
        win = F.unfold(xp[:, :, y0 : y1 + 2 * pad], WINDOW)  # (N, WINDOW^2, rows * W)
        out.append(win.median(dim=1).values.reshape(n, 1, y1 - y0, w))
    return torch.cat(out, dim=2)


def acts_at(n: int, min_spp: int = 2) -> bool:
    """Whether the clamp acts on ``n`` samples per pixel: it needs a variance (2 or more) and at
    least ``consistency_min_spp``."""
    return n >= max(2, min_spp)


def bounds(mean: torch.Tensor, var_mean: torch.Tensor, n: int, k: float,
           box: str = "mean") -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)``, each ``(B, C, H, W)``, from per-pixel means and variances of the mean
    (``(B, C, H, W)``, :func:`mcdenoise.data.stats.pixel_stats`) of ``n >= 2`` samples. The
    shrinkage is the module's, written on the variance of the mean (the sample variance over
    ``n``: the same weights). ``box``: the neighbourhood's variance is the ``"mean"`` or the
    ``"median"`` of the WINDOW x WINDOW box (the median: a light's or a firefly's pixels in the box
    do not lend their variance to the dark pixels beside them)."""
    b, c, h, w = var_mean.shape
    pad = WINDOW // 2
    flat = var_mean.reshape(b * c, 1, h, w)
    if box == "median":
        nb = _box_median(flat)
    else:
        # Replicate padding: a border pixel's neighbourhood is the image, not zeros that would shrink it.
        nb = F.avg_pool2d(F.pad(flat, [pad] * 4, mode="replicate"), WINDOW, stride=1)
    shrunk = ((n - 1) * var_mean + PRIOR * nb.reshape(b, c, h, w)) / (n - 1 + PRIOR)
    half = k * shrunk.sqrt()
    return mean - half, mean + half


def sample_bounds(samples: torch.Tensor, k: float, box: str = "mean") -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)``, each ``(B, C, H, W)``, from per-sample ``(B, S, C, H, W)`` values, ``S >= 2``
    (``box``: :func:`bounds`)."""
    s = samples.shape[1]
    mean = samples.mean(dim=1)
    # Two passes, written out: torch.var_mean over the sample axis took 0.89 s at 1080p, 8 spp on
    # 2 cores, this 0.17 s (the same numbers to float32 rounding).
    var_mean = (samples - mean.unsqueeze(1)).square_().sum(dim=1).div_((s - 1) * s)
    return bounds(mean, var_mean, s, k, box)


def consistency_clamp(out: torch.Tensor, samples: torch.Tensor, k: float | None, min_spp: int = 2,
                      box: str = "mean") -> torch.Tensor:
    """``out`` (B, 3, H, W) clamped to ``k`` shrunk standard errors around the mean of ``samples``
    (B, S, 3, H, W); unchanged for ``k`` None or fewer than ``max(2, min_spp)`` samples
    (``box``: :func:`bounds`)."""
    if k is None or not acts_at(samples.shape[1], min_spp):
        return out
    lo, hi = sample_bounds(samples.to(out.dtype), k, box)
    return torch.minimum(torch.maximum(out, lo), hi)


def pixel_consistency_clamp(out: np.ndarray, mean: np.ndarray, var_mean: np.ndarray | None, n: int,
                            k: float | None, min_spp: int = 2, box: str = "mean") -> np.ndarray:
    """A pixel model's ``out`` (3, H, W) clamped like :func:`consistency_clamp`, from the input's
    per-pixel ``mean`` and variance of the mean ``var_mean`` (3, H, W) over ``n`` samples.

    A pixel model sees no samples, so inference applies this after the model where the input has
    the statistics (an image folder of ``mcdenoise render``, or its first k samples in ``eval``).
    Unchanged for ``k`` None, no variance (a Blender file, a plain colour EXR) or ``n < max(2, min_spp)``."""
    if k is None or var_mean is None or not acts_at(n, min_spp):
        return out
    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))[None]

    lo, hi = bounds(t(mean), t(var_mean), n, k, box)
    return torch.minimum(torch.maximum(t(out), lo), hi)[0].numpy()


def check_consistency(model: str, k: float | None, min_spp: int = 2, box: str = "mean") -> None:
    """Refuse a ``consistency`` that is not None or > 0, a ``consistency_min_spp`` below 1, or a
    ``consistency_box`` other than "mean" or "median" (one line naming the model)."""
    if k is not None and not k > 0:
        raise ValueError(f"{model}: consistency must be a number of standard errors > 0 or None, got {k}")
    if isinstance(min_spp, bool) or not isinstance(min_spp, int) or min_spp < 1:
        raise ValueError(f"{model}: consistency_min_spp must be a whole number of samples >= 1, got {min_spp!r}")
    if box not in ("mean", "median"):
        raise ValueError(f"{model}: consistency_box must be 'mean' or 'median', got {box!r}")
