"""KPCN's network input (Bako, Vogels et al. 2017, Sec. 4.3 and 5.1): per branch, the transformed
colour, its gradients and variance, and the feature buffers' gradients and variances.

:func:`kpcn_features` builds them from a batch for a :class:`~mcdenoise.models.kpcn.KPCNConfig`;
:func:`window_variance` is the ``pixel`` preset's variance estimate for inputs without samples.
The module docstring of :mod:`mcdenoise.models.kpcn` says what each channel is and why.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from mcdenoise.color import luminance
from mcdenoise.data.channels import variance_name
from mcdenoise.models.emitters import as_reflectance

__all__ = ["FEATURES_PER_BRANCH", "kpcn_features", "window_variance"]

#: colour (3) + gradients x/y of colour, normal, albedo, depth (2 x 10) + colour variance (1) +
#: normal, albedo, depth variances (3).
FEATURES_PER_BRANCH = 27


def _lum(x: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B, 1, H, W) luminance (Rec. 709 weights), e.g. of RGB variances (Sec. 5.1)."""
    return luminance(x, 1, keepdims=True)


def _grad_xy(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences of (B, C, H, W); the last column/row gets 0 (no neighbour)."""
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    gx[..., :, :-1] = x[..., :, 1:] - x[..., :, :-1]
    gy[..., :-1, :] = x[..., 1:, :] - x[..., :-1, :]
    return gx, gy


def window_variance(x: torch.Tensor, k: int) -> torch.Tensor:
    """(B, C, H, W) -> (B, C, H, W): the variance of ``x`` over the k x k square around each pixel,
    counting only pixels inside the image (so a tile with k // 2 pixels of overlap sees the
    whole image's values). Noise and texture alike raise it: it stands in for the variance of the
    mean where the input has no samples, and the network is trained with it (``variance="window"``)."""
    xf = x.double()  # E[x^2] - E[x]^2 cancels catastrophically in float32 on bright, flat regions
    mean = F.avg_pool2d(xf, k, stride=1, padding=k // 2, count_include_pad=False)
    mean_sq = F.avg_pool2d(xf * xf, k, stride=1, padding=k // 2, count_include_pad=False)
    return (mean_sq - mean * mean).clamp_min(0).to(x.dtype)


def kpcn_features(batch: dict[str, torch.Tensor], config: Any) -> dict[str, torch.Tensor]:
    """Network inputs per branch: name -> (B, FEATURES_PER_BRANCH, H, W); channels 0:3 are the colour.
    ``config`` is a :class:`~mcdenoise.models.kpcn.KPCNConfig` (not imported: that module imports this one).

    Branch names are ``diffuse`` and ``specular`` (``split``) or ``radiance``. Every channel of a
    pixel depends only on that pixel and its right/lower neighbour (gradients), never on
    statistics of the whole input, so tiles of an image see the same features as the image.
    """
    eps = config.eps
    a_name, n_name, d_name = config.feature_channels()
    albedo = as_reflectance(batch[a_name])
    normal = batch[n_name]
    depth = batch[d_name].clamp_min(0)
    # log(1 + d/s): a fixed map (no per-crop maximum); its variance by Eq. 5's first-order rule,
    # h'(d) = 1 / (s + d).
    s = config.depth_scale
    depth_f = torch.log1p(depth / s)
    window = config.variance == "window"
    k = config.variance_window
    if window:  # each variance measured in the domain the network sees
        feat_var = torch.cat([window_variance(normal, k).mean(dim=1, keepdim=True),
                              _lum(window_variance(albedo, k)), window_variance(depth_f, k)], dim=1)
    else:
        feat_var = torch.cat(
            [
                batch[variance_name(n_name)].mean(dim=1, keepdim=True),
                _lum(batch[variance_name(a_name)]),
                batch[variance_name(d_name)] / (s + depth) ** 2,
            ],
            dim=1,
        )
    feat_grads = [_grad_xy(f) for f in (normal, albedo, depth_f)]

    def branch(color: torch.Tensor, var: torch.Tensor | None) -> torch.Tensor:
        if var is None:
            var = window_variance(color, k)
        gx, gy = _grad_xy(color)
        return torch.cat(
            [color, gx, gy, *[g for pair in feat_grads for g in pair], _lum(var), feat_var], dim=1
        )

    out: dict[str, torch.Tensor] = {}
    if config.split:
        diffuse, specular = batch["diffuse"], batch["specular"].clamp_min(0)
        out["diffuse"] = branch(diffuse / (albedo + eps),
                                None if window else batch[variance_name("diffuse")] / (albedo + eps) ** 2)
        # Eq. 5 with h(x) = log(1 + x): h'(x)^2 = 1 / (1 + x)^2.
        out["specular"] = branch(torch.log1p(specular),
                                 None if window else batch[variance_name("specular")] / (1 + specular) ** 2)
    else:
        radiance = batch["radiance"].clamp_min(0)
        out["radiance"] = branch(torch.log1p(radiance),
                                 None if window else batch[variance_name("radiance")] / (1 + radiance) ** 2)
    return out
