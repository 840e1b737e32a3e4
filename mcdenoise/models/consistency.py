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

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["PRIOR", "WINDOW", "bounds", "sample_bounds", "consistency_clamp", "pixel_consistency_clamp", "check_consistency"]

#: Weight of the neighbourhood's variance, in samples (chosen on held-out images: 0 left pixels
#: whose few samples agree stuck at their mean, and cost 2.4-5.4 dB of PSNR at 4-8 spp:
#: ``scripts/consistency_probe.py ... --prior 0``).
PRIOR = 2.0
#: Side of the box the neighbourhood's variance is averaged over.
WINDOW = 5


def bounds(mean: torch.Tensor, var_mean: torch.Tensor, n: int, k: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)``, each ``(B, C, H, W)``, from per-pixel means and variances of the mean
    (``(B, C, H, W)``, :func:`mcdenoise.data.stats.pixel_stats`) of ``n >= 2`` samples. The
    shrinkage is the module's, written on the variance of the mean (the sample variance over
    ``n``: the same weights)."""
    b, c, h, w = var_mean.shape
    pad = WINDOW // 2
    # Replicate padding: a border pixel's neighbourhood is the image, not zeros that would shrink it.
    box = F.avg_pool2d(F.pad(var_mean.reshape(b * c, 1, h, w), [pad] * 4, mode="replicate"), WINDOW, stride=1)
    shrunk = ((n - 1) * var_mean + PRIOR * box.reshape(b, c, h, w)) / (n - 1 + PRIOR)
    half = k * shrunk.sqrt()
    return mean - half, mean + half


def sample_bounds(samples: torch.Tensor, k: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(lo, hi)``, each ``(B, C, H, W)``, from per-sample ``(B, S, C, H, W)`` values, ``S >= 2``."""
    s = samples.shape[1]
    mean = samples.mean(dim=1)
    # Two passes, written out: torch.var_mean over the sample axis took 0.89 s at 1080p, 8 spp on
    # 2 cores, this 0.17 s (the same numbers to float32 rounding).
    var_mean = (samples - mean.unsqueeze(1)).square_().sum(dim=1).div_((s - 1) * s)
    return bounds(mean, var_mean, s, k)


def consistency_clamp(out: torch.Tensor, samples: torch.Tensor, k: float | None, min_spp: int = 2) -> torch.Tensor:
    """``out`` (B, 3, H, W) clamped to ``k`` shrunk standard errors around the mean of ``samples``
    (B, S, 3, H, W); unchanged for ``k`` None or fewer than ``max(2, min_spp)`` samples."""
    if k is None or samples.shape[1] < max(2, min_spp):
        return out
    lo, hi = sample_bounds(samples.to(out.dtype), k)
    return torch.minimum(torch.maximum(out, lo), hi)


def pixel_consistency_clamp(out: np.ndarray, mean: np.ndarray, var_mean: np.ndarray | None, n: int,
                            k: float | None, min_spp: int = 2) -> np.ndarray:
    """A pixel model's ``out`` (3, H, W) clamped like :func:`consistency_clamp`, from the input's
    per-pixel ``mean`` and variance of the mean ``var_mean`` (3, H, W) over ``n`` samples.

    A pixel model sees no samples, so inference applies this after the model where the input has
    the statistics (an image folder of ``mcdenoise render``, or its first k samples in ``eval``).
    Unchanged for ``k`` None, no variance (a Blender file, a plain colour EXR) or ``n < max(2, min_spp)``."""
    if k is None or var_mean is None or n < max(2, min_spp):
        return out
    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))[None]

    lo, hi = bounds(t(mean), t(var_mean), n, k)
    return torch.minimum(torch.maximum(t(out), lo), hi)[0].numpy()


def check_consistency(model: str, k: float | None, min_spp: int = 2) -> None:
    """Refuse a ``consistency`` that is not None or > 0, or a ``consistency_min_spp`` below 1 (one
    line naming the model)."""
    if k is not None and not k > 0:
        raise ValueError(f"{model}: consistency must be a number of standard errors > 0 or None, got {k}")
    if isinstance(min_spp, bool) or not isinstance(min_spp, int) or min_spp < 1:
        raise ValueError(f"{model}: consistency_min_spp must be a whole number of samples >= 1, got {min_spp!r}")
