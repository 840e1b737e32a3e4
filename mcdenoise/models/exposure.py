"""Autoexposure: a model that scales each image to a fixed brightness before its network and back
after it is exactly exposure-equivariant (the same picture ten times brighter comes out ten times
brighter, filtered the same way).

The scale is ``key / L``, ``L`` the geometric mean of the image's luminance over 8x8-pixel blocks
(blocks averaging the noise; blocks darker than 1e-6 ignored), as Open Image Denoise's
autoexposure does for HDR input. Training computes it per crop; inference on the whole image, once,
before tiling (``batch["exposure_scale"]``), so every tile of an image gets the same scale.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from mcdenoise.data.channels import exposure_power

__all__ = ["EXPOSURE_SCALE", "BLOCK", "autoexposure_scale", "scale_batch", "unscale", "batch_exposure", "check_key"]

#: Batch entry with a precomputed ``(B,)`` scale (the whole image's, given to each tile).
EXPOSURE_SCALE = "exposure_scale"
#: Side of the blocks whose luminance the geometric mean is taken over.
BLOCK = 8
_DARK = 1e-6


@torch.no_grad()
def autoexposure_scale(colour: torch.Tensor, key: float) -> torch.Tensor:
    """``(B, 3, H, W)`` linear radiance (or ``(B, S, 3, H, W)`` samples, averaged) -> ``(B,)``
    scale ``key / geometric-mean block luminance``; 1 for an image with no lit block."""
    if colour.dim() == 5:
        colour = colour.mean(dim=1)
    c = colour.to(torch.promote_types(colour.dtype, torch.float32)).clamp_min(0)  # bf16 -> f32; f64 stays
    lum = 0.2126 * c[:, 0:1] + 0.7152 * c[:, 1:2] + 0.0722 * c[:, 2:3]
    blocks = F.avg_pool2d(lum, BLOCK, ceil_mode=True).flatten(1)
    lit = blocks > _DARK
    n = lit.sum(dim=1)
    log_mean = torch.where(lit, blocks.clamp_min(_DARK).log(), torch.zeros_like(blocks)).sum(dim=1) / n.clamp_min(1)
    scale = key / log_mean.exp()
    return torch.where(n > 0, scale, torch.ones_like(scale))


def scale_batch(batch: dict[str, torch.Tensor], scale: torch.Tensor) -> dict[str, torch.Tensor]:
    """``batch`` with every radiance-like channel times ``scale`` ``(B,)``, variances times its
    square (:func:`~mcdenoise.data.channels.exposure_power`); other entries as they are."""
    out = dict(batch)
    for name, t in batch.items():
        p = exposure_power(name)  # 0 for guides, scene features and the scale itself
        if p:
            s = scale.to(t.dtype).view(-1, *([1] * (t.dim() - 1)))
            out[name] = t * s ** p
    return out


def batch_exposure(batch: dict[str, torch.Tensor], colour: torch.Tensor, key: float) -> torch.Tensor:
    """The ``(B,)`` scale for ``batch``: the precomputed ``batch["exposure_scale"]`` when given, else
    measured on ``colour``."""
    given = batch.get(EXPOSURE_SCALE)
    if given is not None:
        return given.reshape(-1).to(colour.device, torch.promote_types(colour.dtype, torch.float32))
    return autoexposure_scale(colour, key)


def unscale(out: torch.Tensor, scale: torch.Tensor | None) -> torch.Tensor:
    """``(B, 3, H, W)`` output at the autoexposure scale back to the input's exposure."""
    return out if scale is None else out / scale.to(out.dtype).view(-1, 1, 1, 1)


def check_key(model: str, key: float | None) -> None:
    """Refuse an autoexposure key that is not None or > 0 (one line naming the model)."""
    if key is not None and not key > 0:
        raise ValueError(f"{model}: autoexposure must be a key > 0 or None, got {key}")
