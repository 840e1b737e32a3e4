"""List the registered denoisers: presets, parameters, FLOPs per pixel, inputs and channels."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import torch
from torch.utils.flop_counter import FlopCounterMode

from mcdenoise.models.registry import Denoiser, ModelEntry, list_models, synthetic_batch

#: Sample models are measured at this spp, as the issue asks; pixel models ignore it.
FLOPS_SPP = 8
#: Big enough that U-Nets see several levels, small enough to run every preset in seconds.
FLOPS_SIZE = 64


def add_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--preset", action="append", default=None,
                   help="only these presets (repeatable; default: all)")
    p.add_argument("--no-flops", action="store_true", help="skip the FLOP count (faster)")


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


def describe(entry: ModelEntry, presets: list[str] | None, with_flops: bool) -> dict[str, Any]:
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
        out["presets"][preset] = info
    return out


def run(args: argparse.Namespace) -> int:
    torch.manual_seed(0)
    rows = [describe(e, args.preset, not args.no_flops) for e in list_models()]
    if args.json:
        json.dump(rows, sys.stdout, indent=2)
        print()
        return 0
    for row in rows:
        print(f"{row['name']}  ({row['paper']})")
        if row["description"]:
            print(f"    {row['description']}")
        for preset, info in row["presets"].items():
            flops = ""
            if "flops_per_pixel" in info:
                at = f" at {info['flops_spp']} spp" if "flops_spp" in info else ""
                flops = f", {info['flops_per_pixel'] / 1e6:.2f} MFLOP/pixel{at}"
            print(f"    {preset:<8} {info['parameters']:>11,d} params{flops}, input: {info['input_kind']}")
        first = next(iter(row["presets"].values()), None)
        if first is not None:
            print(f"    channels: {', '.join(first['channels'])}")
    return 0
