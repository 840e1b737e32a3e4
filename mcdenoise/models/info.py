"""What `mcdenoise models` reports about each registered model: parameters, FLOPs, inputs."""

from __future__ import annotations

from typing import Any

import torch
from torch.utils.flop_counter import FlopCounterMode

from mcdenoise.models.registry import Denoiser, ModelEntry, synthetic_batch

__all__ = ["FLOPS_SPP", "FLOPS_SIZE", "count_parameters", "flops_per_pixel", "describe"]

#: Sample models are measured at this spp, as the issue asks; pixel models ignore it.
FLOPS_SPP = 8
#: Big enough that U-Nets see several levels, small enough to run every preset in seconds.
FLOPS_SIZE = 64


def count_parameters(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def flops_per_pixel(model: Denoiser, *, spp: int = FLOPS_SPP, size: int = FLOPS_SIZE) -> float:
    """Convolution/matmul FLOPs of one forward pass per output pixel (a multiply-add counts 2).

    Counted by ``torch.utils.flop_counter`` on a synthetic ``size x size`` input; element-wise work
    (activations, kernel application by gather/splat loops) is not included.
    """
    batch = synthetic_batch(model, spp=spp, height=size, width=size)
    model.eval()
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        model(batch)
    return counter.get_total_flops() / float(size * size)


def describe(entry: ModelEntry, presets: list[str] | None = None, with_flops: bool = True) -> dict[str, Any]:
    """name, paper, description and, per preset: parameters, input kind, channels, FLOPs/pixel.

    Models with a ``reparameterize()`` method (WSKP's RepVGG blocks fold into one conv each) have
    a training form and a smaller inference form; the paper times the latter, so a preset of such
    a model also gets ``"inference": {"parameters", "flops_per_pixel"}`` for the folded network.
    """
    out: dict[str, Any] = {"name": entry.name, "paper": entry.paper, "description": entry.description,
                           "presets": {}}
    for preset in entry.presets:
        if presets and preset not in presets:
            continue
        model = entry.cls(entry.config(preset))
        info: dict[str, Any] = {
            "parameters": count_parameters(model),
            "input_kind": model.input_kind,
            "channels": model.required_channels(),
        }
        if with_flops:
            info["flops_per_pixel"] = flops_per_pixel(model)
            if model.input_kind == "samples":
                info["flops_spp"] = FLOPS_SPP
        if callable(getattr(model, "reparameterize", None)):
            folded = model.reparameterize()  # in place: the training form's figures are taken
            inference: dict[str, Any] = {"parameters": count_parameters(folded)}
            if with_flops:
                inference["flops_per_pixel"] = flops_per_pixel(folded)
            info["inference"] = inference
        out["presets"][preset] = info
    return out
