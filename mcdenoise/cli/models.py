"""List the registered denoisers: presets, parameters, FLOPs per pixel, inputs and channels."""

from __future__ import annotations

import argparse
import json
import sys


def add_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--preset", action="append", default=None,
                   help="only these presets (repeatable; default: all)")
    p.add_argument("--no-flops", action="store_true", help="skip the FLOP count (faster)")


def run(args: argparse.Namespace) -> int:
    # Imported here: torch costs a second or two, which `mcdenoise --version` should not pay.
    import torch

    from mcdenoise.models.info import describe
    from mcdenoise.models.registry import list_models

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
