"""List the registered denoisers: presets, parameters, inputs, channels, shipped weights; FLOPs
per pixel with ``--flops`` (counting them runs every preset once: ~40 s for all models on 2 cores,
so the default listing leaves them out and takes a few seconds)."""

from __future__ import annotations

import argparse
import json
import sys


def add_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--preset", action="append", default=None,
                   help="only these presets (repeatable; default: all)")
    p.add_argument("--model", action="append", default=None,
                   help="only these models (repeatable; default: all registered)")
    p.add_argument("--flops", action="store_true",
                   help="also count FLOPs per pixel (runs every listed preset once: ~40 s for all models)")
    # The old opt-out, now the default; kept so existing scripts still run.
    p.add_argument("--no-flops", action="store_true", help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    # Imported here: torch costs a second or two, which `mcdenoise --version` should not pay.
    import torch

    from mcdenoise.models.info import describe
    from mcdenoise.models.registry import list_models
    from mcdenoise.models.weights import shipped

    torch.manual_seed(0)
    entries = list_models()
    if args.model:
        unknown = sorted(set(args.model) - {e.name for e in entries})
        if unknown:
            print(f"mcdenoise models: unknown model(s) {', '.join(unknown)}; "
                  f"registered: {', '.join(e.name for e in entries)}", file=sys.stderr)
            return 2
        entries = [e for e in entries if e.name in args.model]
    if args.preset:
        known = {p for e in entries for p in e.presets}
        bogus = sorted(set(args.preset) - known)
        if bogus:
            print(f"mcdenoise models: no {'selected ' if args.model else ''}model has preset(s) {', '.join(bogus)}; "
                  f"presets: {', '.join(sorted(known))}", file=sys.stderr)
            return 2
    have = {(s.name, s.preset) for s in shipped()}
    rows = [describe(e, args.preset, args.flops and not args.no_flops) for e in entries]
    for row in rows:
        for preset, info in row["presets"].items():
            info["shipped_weights"] = (row["name"], preset) in have
    if args.json:
        json.dump(rows, sys.stdout, indent=2)
        print()
        return 0
    for row in rows:
        print(f"{row['name']}  ({row['paper']})")
        if row["description"]:
            print(f"    {row['description']}")
        width = max([8, *(len(p) for p in row["presets"])])
        for preset, info in row["presets"].items():
            flops = ""
            if "flops_per_pixel" in info:
                at = f" at {info['flops_spp']} spp" if "flops_spp" in info else ""
                flops = f", {_mflop(info['flops_per_pixel'])} MFLOP/pixel{at}"
            form = ", training form" if "inference" in info else ""
            weights = ", shipped weights" if info["shipped_weights"] else ""
            print(f"    {preset:<{width}} {info['parameters']:>11,d} params{flops}, input: {info['input_kind']}{form}{weights}")
            if "inference" in info:
                inf = info["inference"]
                flops = f", {_mflop(inf['flops_per_pixel'])} MFLOP/pixel" if "flops_per_pixel" in inf else ""
                print(f"    {'':<{width}} {inf['parameters']:>11,d} params{flops}, inference form (re-parameterised)")
        first = next(iter(row["presets"].values()), None)
        if first is not None:
            print(f"    channels: {', '.join(first['channels'])}")
    if not args.json:
        names = ", ".join(f"{n} ({p})" for n, p in sorted(have)) or "none"
        print(f"\nShipped weights (usable by name in denoise/eval): {names}."
              + ("" if args.flops else " FLOPs per pixel: add --flops."))
    return 0


def _mflop(flops: float) -> str:
    """MFLOP with 3 significant digits below 1 (WSKP's 0.0764 vs 0.0546), 2 decimals above."""
    m = flops / 1e6
    return f"{m:.3g}" if m < 1 else f"{m:,.2f}"
