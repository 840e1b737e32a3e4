"""Peak memory of `mcdenoise denoise` on a large image folder through every sample model (issue 11).

    .venv/bin/python benchmarks/bench_denoise_memory.py --predict                  # 3840x2160, 8 spp, modelled
    .venv/bin/python benchmarks/bench_denoise_memory.py --size 3840x2160 --spp 8   # measured (hours on 2 cores)
    .venv/bin/python benchmarks/bench_denoise_memory.py --size 256x256 --max-memory 128M --models sbmc layer

Measured mode writes a synthetic image folder (random but plausible samples of every channel the
sample models read, streamed to ``samples.bin`` a band of rows at a time) and runs
``mcdenoise denoise FOLDER -o OUT.exr --model W --max-memory M`` for each model (small preset,
random weights) in a fresh process, reporting that process's peak resident set (``ru_maxrss``:
everything -- Python, torch, weights, the reader, the tile, the whole-image output) and its
wall time, against the 8 GB target.

``--predict`` runs no model on the image: it prints the tile plan ``--tile auto`` picks and the
peak the plan is sized for: the measured per-pixel cost of one window
(:func:`mcdenoise.infer.memory.measure_cost`, on small probes) plus the whole-image output.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET = 8 << 30
SAMPLE_MODELS = ("sbmc", "sbmc_gather", "pixel_splat", "pixel_gather", "layer", "layer_weighted", "layer_optimized")


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def _write_folder(path: Path, width: int, height: int, spp: int, channels: list[str]) -> Path:
    import numpy as np

    from mcdenoise.data.format import ImageMeta, SampleWriter
    from mcdenoise.data.channels import num_components

    meta = ImageMeta(width=width, height=height, spp=spp, channels=channels, scene="bench",
                     scene_features={"fov": 40.0, "aperture_radius": 0.05, "focus_distance": 4.0})
    rng = np.random.default_rng(0)
    writer = SampleWriter(path, meta)
    band = 64
    for name in channels:
        c = num_components(name)
        for y0 in range(0, height, band):
            y1 = min(height, y0 + band)
            x = rng.random((spp, c, y1 - y0, width), dtype=np.float32)
            if name.startswith("normal"):
                x = x * 2 - 1
            elif name.startswith("depth"):
                x = x * 10
            elif name in ("radiance", "diffuse", "specular"):
                x = x * 2
            writer.write(name, x, rows=slice(y0, y1))
    return writer.finish()


def _child(args: argparse.Namespace) -> int:
    from mcdenoise.cli.main import main

    t = time.perf_counter()
    rc = main(["denoise", args.folder, "-o", args.out, "--model", args.weights, "--max-memory", args.max_memory,
               "--device", "cpu", "--force"])
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(json.dumps({"rc": rc, "peak": peak, "seconds": time.perf_counter() - t}))
    return rc


def _predict(models: list[str], width: int, height: int, spp: int, budget: int) -> None:
    import torch

    from mcdenoise.infer.run import BUDGET_FRACTION, memory_cost, tile_plan
    from mcdenoise.models import build_model

    torch.manual_seed(0)
    print(f"{width}x{height}, {spp} spp, --max-memory {budget / 2**30:.1f} GiB (predicted, no model run on the image)")
    for name in models:
        model = build_model(name, "small").eval()
        t = time.perf_counter()
        plan = tile_plan(model, height, width, spp=spp, device="cpu", max_memory=budget)
        cost = memory_cost(model, spp, torch.device("cpu"))
        window = min(plan.window, height) * min(plan.window, width)
        peak = cost.bytes(window) + 3 * 4 * height * width
        print(f"  {name:16s} {len(plan):4d} tiles of {plan.core} px (+{plan.overlap} overlap)  "
              f"{cost.per_pixel:7.0f} B/pixel  window {peak / 2**30:5.2f} GiB  "
              f"{'<' if peak < TARGET else '>='} 8 GB  ({time.perf_counter() - t:.0f} s to plan)", flush=True)
    print(f"  (a window gets {BUDGET_FRACTION:.0%} of the budget; the rest is for reading buffers and Python)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=_size, default=(3840, 2160), help="WxH (default 3840x2160)")
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--models", nargs="+", default=list(SAMPLE_MODELS))
    ap.add_argument("--max-memory", default="4G")
    ap.add_argument("--predict", action="store_true", help="plan and model the peak only (fast)")
    ap.add_argument("--workdir", type=Path, default=None, help="where the synthetic folder goes (default: a temp dir)")
    ap.add_argument("--child", nargs=4, metavar=("FOLDER", "OUT", "WEIGHTS", "MAXMEM"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        ns = argparse.Namespace(folder=args.child[0], out=args.child[1], weights=args.child[2], max_memory=args.child[3])
        return _child(ns)
    from mcdenoise.infer.memory import parse_memory

    width, height = args.size
    budget = parse_memory(args.max_memory)
    if args.predict:
        _predict(args.models, width, height, args.spp, budget)
        return 0
    import torch
    from safetensors.torch import save_file

    from mcdenoise.models import build_model

    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_denoise_"))
    work.mkdir(parents=True, exist_ok=True)
    channels: list[str] = []
    for name in args.models:
        for c in build_model(name, "small").required_channels():
            if c != "scene_features" and c not in channels:
                channels.append(c)
    folder = work / f"img_{width}x{height}_{args.spp}spp"
    have: list[str] = []
    if (folder / "meta.json").exists():
        have = json.loads((folder / "meta.json").read_text()).get("channels", [])
    if not set(channels) <= set(have):  # a folder written for other models lacks channels: write it again
        if folder.exists():
            shutil.rmtree(folder)
        t = time.perf_counter()
        _write_folder(folder, width, height, args.spp, channels)
        print(f"wrote {folder} in {time.perf_counter() - t:.0f} s", flush=True)
    print(f"{width}x{height}, {args.spp} spp, --max-memory {args.max_memory}: peak resident set of `mcdenoise denoise`")
    for name in args.models:
        torch.manual_seed(0)
        weights = work / f"{name}.safetensors"
        save_file(build_model(name, "small").state_dict(), str(weights), metadata={"model": name, "preset": "small"})
        cmd = [sys.executable, __file__, "--child", str(folder), str(work / f"{name}.exr"), str(weights), args.max_memory]
        res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "MALLOC_MMAP_THRESHOLD_": "65536"})
        lines = res.stdout.strip().splitlines()
        try:
            doc = json.loads(lines[-1])
        except (IndexError, ValueError):
            print(f"  {name:16s} failed: {res.stderr.strip().splitlines()[-1:] or res.returncode}")
            continue
        plan = next((ln for ln in lines if ln.startswith("ran ")), "")
        if res.returncode != 0 or not plan:  # the child caught the error and still printed its peak
            err = res.stderr.strip().splitlines()[-1:] or [f"exit {res.returncode}"]
            print(f"  {name:16s} failed: {err[0]}", flush=True)
            continue
        print(f"  {name:16s} peak {doc['peak'] / 2**30:5.2f} GiB  {'<' if doc['peak'] < TARGET else '>='} 8 GB  "
              f"{doc['seconds']:6.0f} s  {plan}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
