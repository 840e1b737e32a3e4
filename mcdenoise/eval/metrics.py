"""Image metrics with stated conventions (mirrored in docs/METRICS.md).

Shared conventions:

* ``x`` is the estimate (denoised or noisy), ``y`` the reference; same shape ``(C, H, W)`` or
  ``(B, C, H, W)``, linear HDR radiance unless a metric says it tonemaps.
* numpy inputs give a Python ``float``; torch inputs give a 0-dim tensor (differentiable, on the
  inputs' device) -- or ``(B,)`` with ``reduction="none"``.
* Each metric is computed per image, averaged over channels and pixels with equal weight, then
  averaged over the batch (``reduction="mean"``).
* ``border`` crops that many pixels from each side of both images before anything else.
* ``eps`` defaults to 1e-2 where a metric divides.
* Tonemapped metrics (PSNR, SSIM, DSSIM) first apply :func:`tonemap`, by default ``"reinhard"``:
  the sRGB transfer function of ``max(v, 0) / (1 + max(v, 0))`` -- values in [0, 1], peak 1.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Union

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "mse",
    "relmse",
    "smape",
    "l1",
    "rel_l1",
    "psnr",
    "ssim",
    "dssim",
    "flip",
    "flip_available",
    "tonemap",
    "METRICS",
    "compute_metrics",
    "TONEMAPS",
    "LOG_WHITE",
]

Array = Union[np.ndarray, torch.Tensor]
TONEMAPS = ("reinhard", "srgb", "log", "none")
#: White point of the ``log`` tonemap (same as the PNG previews of :mod:`mcdenoise.io.exr`).
LOG_WHITE = 100.0


def _prepare(x: Array, y: Array, border: int) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """To ``(B, C, H, W)`` tensors (numpy -> float64 CPU tensors), border-cropped."""
    is_np = not isinstance(x, torch.Tensor)
    if is_np != (not isinstance(y, torch.Tensor)):
        raise TypeError("x and y must both be numpy arrays or both torch tensors")
    if is_np:
        xt = torch.from_numpy(np.asarray(x, dtype=np.float64))
        yt = torch.from_numpy(np.asarray(y, dtype=np.float64))
    else:
        xt, yt = x, y
        if not xt.is_floating_point():
            xt = xt.float()
        if yt.dtype != xt.dtype:
            yt = yt.to(xt.dtype)
    if xt.shape != yt.shape:
        raise ValueError(f"x has shape {tuple(xt.shape)}, y has shape {tuple(yt.shape)}: they must match")
    if xt.ndim == 3:
        xt, yt = xt[None], yt[None]
    if xt.ndim != 4:
        raise ValueError(f"expected (C, H, W) or (B, C, H, W), got shape {tuple(xt.shape)}")
    if border < 0:
        raise ValueError(f"border must be >= 0, got {border}")
    if border:
        h, w = xt.shape[-2:]
        if 2 * border >= min(h, w):
            raise ValueError(f"border {border} leaves nothing of a {h}x{w} image")
        xt = xt[..., border:-border, border:-border]
        yt = yt[..., border:-border, border:-border]
    return xt, yt, is_np


def _finish(per_image: torch.Tensor, is_np: bool, reduction: str) -> Any:
    if reduction == "mean":
        v = per_image.mean()
        return float(v) if is_np else v
    if reduction == "none":
        return per_image.detach().cpu().numpy() if is_np else per_image
    raise ValueError(f"reduction must be 'mean' or 'none', got {reduction!r}")


def _per_image_mean(t: torch.Tensor) -> torch.Tensor:
    return t.flatten(1).mean(dim=1)


def tonemap(v: Array, kind: str = "reinhard") -> Array:
    """Tonemap linear radiance to [0, 1] (``none`` returns the input unchanged).

    * ``reinhard``: ``srgb_oetf(v' / (1 + v'))`` with ``v' = max(v, 0)``;
    * ``srgb``: ``srgb_oetf(clip(v, 0, 1))``;
    * ``log``: ``clip(log1p(v') / log1p(100), 0, 1)``;

    where ``srgb_oetf(u) = 12.92 u`` for ``u <= 0.0031308`` else ``1.055 u^(1/2.4) - 0.055``.
    """
    if kind not in TONEMAPS:
        raise ValueError(f"unknown tonemap {kind!r}; choose one of {TONEMAPS}")
    if kind == "none":
        return v
    is_np = not isinstance(v, torch.Tensor)
    t = torch.from_numpy(np.asarray(v, dtype=np.float64)) if is_np else v
    t = t.clamp_min(0.0)
    if kind == "log":
        out = (torch.log1p(t) / math.log1p(LOG_WHITE)).clamp(0.0, 1.0)
    else:
        u = t / (1.0 + t) if kind == "reinhard" else t.clamp(0.0, 1.0)
        # Clamp inside pow so its gradient stays finite on the linear branch.
        out = torch.where(u <= 0.0031308, 12.92 * u, 1.055 * u.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055)
    return out.numpy() if is_np else out


def mse(x: Array, y: Array, *, border: int = 0, reduction: str = "mean") -> Any:
    """Mean squared error: ``mean((x - y)^2)`` over channels and pixels."""
    xt, yt, is_np = _prepare(x, y, border)
    return _finish(_per_image_mean((xt - yt) ** 2), is_np, reduction)


def relmse(x: Array, y: Array, *, eps: float = 1e-2, border: int = 0, reduction: str = "mean") -> Any:
    """Relative MSE: ``mean((x - y)^2 / (y^2 + eps))``, per channel (no luminance), eps = 1e-2."""
    xt, yt, is_np = _prepare(x, y, border)
    return _finish(_per_image_mean((xt - yt) ** 2 / (yt ** 2 + eps)), is_np, reduction)


def smape(x: Array, y: Array, *, eps: float = 1e-2, border: int = 0, reduction: str = "mean") -> Any:
    """Symmetric MAPE: ``mean(|x - y| / (|x| + |y| + eps))``, eps = 1e-2 (Munkberg & Hasselgren
    2020, Eq. 9). Range [0, 1)."""
    xt, yt, is_np = _prepare(x, y, border)
    return _finish(_per_image_mean((xt - yt).abs() / (xt.abs() + yt.abs() + eps)), is_np, reduction)


def l1(x: Array, y: Array, *, border: int = 0, reduction: str = "mean") -> Any:
    """Mean absolute error: ``mean(|x - y|)``."""
    xt, yt, is_np = _prepare(x, y, border)
    return _finish(_per_image_mean((xt - yt).abs()), is_np, reduction)


def rel_l1(x: Array, y: Array, *, eps: float = 1e-2, border: int = 0, reduction: str = "mean") -> Any:
    """Relative L1: ``mean(|x - y| / (|y| + eps))``, eps = 1e-2."""
    xt, yt, is_np = _prepare(x, y, border)
    return _finish(_per_image_mean((xt - yt).abs() / (yt.abs() + eps)), is_np, reduction)


def psnr(x: Array, y: Array, *, tonemap_kind: str = "reinhard", border: int = 0, reduction: str = "mean") -> Any:
    """PSNR in dB on tonemapped images: ``10 log10(1 / mse(T(x), T(y)))``, peak 1, per image then
    averaged; ``inf`` for identical images. ``T`` = :func:`tonemap` (default ``reinhard``)."""
    xt, yt, is_np = _prepare(x, y, border)
    e = _per_image_mean((tonemap(xt, tonemap_kind) - tonemap(yt, tonemap_kind)) ** 2)
    return _finish(-10.0 * torch.log10(e), is_np, reduction)


def _gaussian_window(sigma: float, radius: int, ref: torch.Tensor) -> torch.Tensor:
    r = torch.arange(-radius, radius + 1, dtype=ref.dtype, device=ref.device)
    g = torch.exp(-(r ** 2) / (2 * sigma ** 2))
    return g / g.sum()


def _filter_valid(t: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable filter of ``(N, 1, H, W)`` with ``g``, 'valid' region only (no padding)."""
    k = g.numel()
    t = F.conv2d(t, g.view(1, 1, 1, k))
    return F.conv2d(t, g.view(1, 1, k, 1))


def ssim(
    x: Array,
    y: Array,
    *,
    tonemap_kind: str = "reinhard",
    border: int = 0,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    reduction: str = "mean",
) -> Any:
    """SSIM (Wang et al. 2004) on tonemapped images with data range 1.

    Gaussian window, sigma 1.5, radius ``int(3.5 * sigma + 0.5)`` (11x11); local statistics with
    population (not sample) covariance; ``C1 = (k1)^2, C2 = (k2)^2`` with k1 = 0.01, k2 = 0.03.
    The SSIM map is computed per channel on the 'valid' region (a window-radius border of the map
    dropped, no padding) and averaged over channels and pixels. Matches
    ``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=0)``.
    """
    xt, yt, is_np = _prepare(x, y, border)
    xt, yt = tonemap(xt, tonemap_kind), tonemap(yt, tonemap_kind)
    radius = int(3.5 * sigma + 0.5)
    b, c, h, w = xt.shape
    if min(h, w) < 2 * radius + 1:
        raise ValueError(f"SSIM needs images of at least {2 * radius + 1}x{2 * radius + 1}, got {h}x{w}")
    g = _gaussian_window(sigma, radius, xt)
    a = xt.reshape(b * c, 1, h, w)
    r = yt.reshape(b * c, 1, h, w)
    mu_a, mu_r = _filter_valid(a, g), _filter_valid(r, g)
    s_aa = _filter_valid(a * a, g) - mu_a ** 2
    s_rr = _filter_valid(r * r, g) - mu_r ** 2
    s_ar = _filter_valid(a * r, g) - mu_a * mu_r
    c1, c2 = k1 ** 2, k2 ** 2
    smap = ((2 * mu_a * mu_r + c1) * (2 * s_ar + c2)) / ((mu_a ** 2 + mu_r ** 2 + c1) * (s_aa + s_rr + c2))
    return _finish(smap.reshape(b, -1).mean(dim=1), is_np, reduction)


def dssim(x: Array, y: Array, **kwargs: Any) -> Any:
    """Structural dissimilarity ``1 - SSIM`` (as in the SBMC paper's tables; not (1 - SSIM) / 2).
    Same arguments and conventions as :func:`ssim`."""
    s = ssim(x, y, **kwargs)
    return 1.0 - s


def flip_available() -> bool:
    """True when the ``flip-evaluator`` package imports."""
    try:
        import flip_evaluator  # noqa: F401
    except ImportError:
        return False
    return True


def flip(x: Array, y: Array, *, border: int = 0, reduction: str = "mean") -> Any:
    """Mean HDR-FLIP error (NVIDIA ``flip-evaluator``, its default HDR settings: 67 pixels per degree,
    exposure range chosen by FLIP) of estimate ``x`` against reference ``y``.

    Needs 3 channels (linear RGB); negative values are clamped to 0. Not differentiable: torch
    inputs give a detached tensor. Raises RuntimeError when ``flip-evaluator`` is not installed.
    """
    try:
        import flip_evaluator
    except ImportError:
        raise RuntimeError("FLIP needs the flip-evaluator package (pip install flip-evaluator)") from None
    xt, yt, is_np = _prepare(x, y, border)
    if xt.shape[1] != 3:
        raise ValueError(f"FLIP needs 3 channels, got {xt.shape[1]}")
    vals = []
    for i in range(xt.shape[0]):
        ref = np.ascontiguousarray(yt[i].detach().cpu().clamp_min(0).permute(1, 2, 0).numpy(), dtype=np.float32)
        tst = np.ascontiguousarray(xt[i].detach().cpu().clamp_min(0).permute(1, 2, 0).numpy(), dtype=np.float32)
        _, mean_err, _ = flip_evaluator.evaluate(ref, tst, "HDR", applyMagma=False)
        vals.append(float(mean_err))
    per = torch.tensor(vals, dtype=torch.float64 if is_np else xt.dtype, device="cpu" if is_np else xt.device)
    return _finish(per, is_np, reduction)


#: Metric name -> function(x, y, **kwargs). ``flip`` is listed only when available.
METRICS: dict[str, Callable[..., Any]] = {
    "mse": mse,
    "relmse": relmse,
    "smape": smape,
    "l1": l1,
    "rel_l1": rel_l1,
    "psnr": psnr,
    "ssim": ssim,
    "dssim": dssim,
}
if flip_available():
    METRICS["flip"] = flip


def compute_metrics(x: Array, y: Array, names: Sequence[str] | None = None, *, border: int = 0) -> dict[str, float]:
    """Every metric in ``names`` (default: all of :data:`METRICS`) as Python floats."""
    out = {}
    for name in names if names is not None else list(METRICS):
        if name not in METRICS:
            raise KeyError(f"unknown metric {name!r}; known: {sorted(METRICS)}")
        v = METRICS[name](x, y, border=border)
        out[name] = float(v.detach()) if isinstance(v, torch.Tensor) else float(v)
    return out
