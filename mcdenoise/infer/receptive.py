"""How far a model looks: its receptive field and the pixel grid its pooling aligns to.

Tiling is exact when (a) every tile's input window reaches at least the receptive field beyond the
pixels it keeps, and (b) tile windows start on multiples of the model's pooling factor (a U-Net's
2x2 pooling must see the same 2x2 groups in the tile as in the whole image).

The receptive field is *measured*, not derived by hand for each architecture: the gradient of an
aligned ``M x M`` block of output pixels with respect to every input is non-zero exactly on the
pixels that block depends on (zero padding and 1x1/3x3 convolutions propagate exact zeros), so the
largest distance of a non-zero gradient from the block is the receptive field. The architecture,
not the widths, decides it, so the measurement runs on a copy of the model with every width shrunk
(:func:`thin_config`), which makes it cheap even for the paper presets.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from mcdenoise.models.registry import Denoiser, synthetic_batch

__all__ = ["alignment", "receptive_field", "measure_receptive_field", "thin_config"]

#: Config fields holding layer widths (ints or nested tuples of ints); shrinking them keeps the
#: architecture's geometry. ``channels`` is a width in kpcn/wskp/wskp_mr, a tuple of channel
#: *names* (strings, left alone) in sbmc/layer.
_WIDTH_FIELDS = ("channels", "embed_width", "fc_width", "context_width", "unet_encoder", "unet_bottleneck",
                 "unet_decoder", "partitioner_widths", "kernel_widths")
_THIN = 3


def _shrink(v: Any) -> Any:
    if isinstance(v, bool) or isinstance(v, str):
        return v
    if isinstance(v, int):
        return min(v, _THIN)
    if isinstance(v, tuple):
        return tuple(_shrink(x) for x in v)
    return v


def thin_config(config: Any) -> Any:
    """``config`` with every width field shrunk to at most 3 (same receptive field, ~no cost)."""
    if not dataclasses.is_dataclass(config):
        return config
    changes = {f.name: _shrink(getattr(config, f.name)) for f in dataclasses.fields(config) if f.name in _WIDTH_FIELDS}
    return dataclasses.replace(config, **changes)


def alignment(model: Denoiser) -> int:
    """Pixel multiple that tile windows must start on so that pooling sees the same pixel groups.

    1 for purely convolutional models; ``2**levels`` for a U-Net; ``2**(levels-1)`` for the
    pyramids of ``wskp_mr`` and ``layer_optimized``.
    """
    from mcdenoise.models.blocks import UNet

    m = 1
    for mod in model.modules():
        if isinstance(mod, UNet):
            m = max(m, mod.multiple)
    levels = getattr(model, "levels", None)  # WSKPMR: pyramid of `levels` resolutions
    if isinstance(levels, int):
        m = max(m, 2 ** (levels - 1))
    cfg = getattr(model, "config", None)
    if getattr(cfg, "hierarchical", False):
        m = max(m, 2 ** (int(cfg.levels) - 1))
    return m


def _support_radius(model: Denoiser, size: int, block: int, spp: int) -> int:
    """Largest distance (pixels, Chebyshev) of an input the central ``block`` of outputs depends on.

    Returns ``size`` when the dependence reaches the border of the ``size x size`` probe (then the
    probe was too small to tell).
    """
    g = torch.Generator().manual_seed(0)
    batch = synthetic_batch(model, spp=spp, height=size, width=size, generator=g)
    leaves = {k: v.requires_grad_(True) for k, v in batch.items() if k != "scene_features"}
    y0 = (size // 2 // block) * block
    with torch.enable_grad():
        out = model(batch)
        out[..., y0 : y0 + block, y0 : y0 + block].sum().backward()
    dep = torch.zeros(size, size, dtype=torch.bool)
    for v in leaves.values():
        grad = v.grad
        if grad is None:
            continue
        dep |= (grad.abs().flatten(0, -3) > 0).any(dim=0)
    ys = torch.nonzero(dep.any(dim=1)).flatten()
    xs = torch.nonzero(dep.any(dim=0)).flatten()
    if len(ys) == 0:
        return 0
    lo = min(int(ys[0]), int(xs[0]))
    hi = max(int(ys[-1]), int(xs[-1]))
    if lo == 0 or hi == size - 1:
        return size
    return max(y0 - lo, hi - (y0 + block - 1))


def _all_paths_open(probe: torch.nn.Module) -> None:
    """Give the thin probe small positive weights, zero-mean unit-variance BatchNorm statistics.

    With random signed weights a 3-channel probe can have every ReLU on some path switched off,
    and the gradient then stops short of the true receptive field (it depended on the global RNG:
    wskp_mr measured 22 or 8 px). Positive weights on positive synthetic inputs keep each ReLU
    active, so the measured support is the architecture's, whatever the trained weights are.
    """
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for p in probe.parameters():
            p.copy_(torch.rand(p.shape, generator=g, dtype=p.dtype) * 0.04 + 0.01)
        for mod in probe.modules():
            if isinstance(mod, torch.nn.modules.batchnorm._BatchNorm) and mod.running_mean is not None:
                mod.running_mean.zero_()
                mod.running_var.fill_(1.0)


def measure_receptive_field(model: Denoiser, *, thin: bool = True, start: int = 48, limit: int = 4096) -> int:
    """Measure the receptive field radius of ``model`` in pixels (see the module docstring).

    The probe image doubles from ``start`` until the dependence stops short of its border.
    ``thin`` measures a width-shrunk copy (same geometry); the model itself is not changed.
    """
    probe = model
    if thin and dataclasses.is_dataclass(getattr(model, "config", None)):
        try:
            probe = type(model)(thin_config(model.config))
        except (ValueError, TypeError):
            probe = model  # a config whose widths cannot shrink: measure the real thing
    probe = probe.eval()  # BatchNorm must use running statistics, not the probe's batch
    if probe is not model:
        _all_paths_open(probe)
    m = alignment(probe)
    spp = 1  # the receptive field does not depend on the sample count
    size = math.ceil(start / m) * m
    while size <= limit:
        r = _support_radius(probe, size, m, spp)
        if r < size:
            return r
        size *= 2
    raise RuntimeError(f"{type(model).__name__}: receptive field exceeds {limit} pixels")


def _config_key(model: Denoiser) -> tuple[str, str]:
    cfg = getattr(model, "config", None)
    return type(model).__qualname__, repr(cfg)


_CACHE: dict[tuple[str, str], int] = {}


def receptive_field(model: Denoiser) -> int:
    """:func:`measure_receptive_field`, remembered per model class and configuration."""
    key = _config_key(model)
    if key not in _CACHE:
        _CACHE[key] = measure_receptive_field(model)
    return _CACHE[key]
