"""Per-pixel statistics of per-sample data (the noisy.exr mean and variance of the mean)."""

from __future__ import annotations

import numpy as np

__all__ = ["pixel_stats"]


def pixel_stats(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel mean and variance of the mean from ``(S, C, H, W)`` samples.

    variance of the mean = unbiased sample variance / S
                         = sum_s (x_s - mean)^2 / ((S - 1) * S);
    it is 0 when S == 1 (no estimate possible). Computed in float64, returned as float32 ``(C, H, W)``.
    """
    x = np.asarray(samples, dtype=np.float64)
    s = x.shape[0]
    mean = x.mean(axis=0)
    if s < 2:
        var = np.zeros_like(mean)
    else:
        var = ((x - mean) ** 2).sum(axis=0) / ((s - 1) * s)
    return mean.astype(np.float32), var.astype(np.float32)
