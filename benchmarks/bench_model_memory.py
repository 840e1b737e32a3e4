"""Peak memory of whole models at a given image size and sample count, one fresh process per run.

    .venv/bin/python benchmarks/bench_model_memory.py --models sbmc pixel_gather --preset small \\
        --size 1920x64 1920x128 --spp 8 --extrapolate 1920x1080
    .venv/bin/python benchmarks/bench_model_memory.py              # every registered model, 256x256, 8 spp
    .venv/bin/python benchmarks/bench_model_memory.py --train      # forward + backward instead
    .venv/bin/python benchmarks/bench_model_memory.py --models sbmc --set kernel_budget_mb=16

Each (model, size) runs in its own subprocess (so one run's allocator state cannot hide another's
peak) with ``MALLOC_MMAP_THRESHOLD_=65536``, so glibc returns large freed blocks to the system and
the resident set follows what is really alive. The child builds the model and a
:func:`mcdenoise.models.registry.synthetic_batch` (float32), resets the peak resident set
(``/proc/self/clear_refs``), runs ``model(batch)`` under ``torch.no_grad()`` (or forward +
backward with ``--train``) and reports:

* ``inputs``: bytes of the input batch (already resident before the call);
* ``rise``: peak resident set during the call minus the resident set just before it: what the
  model itself needs on top of its inputs and weights;
* ``peak``: ``inputs + rise`` (the weights, ~0.1 GB for the largest paper model, left out).

On CUDA (``--device cuda``) the same numbers come from ``torch.cuda.max_memory_allocated``.
``--extrapolate WxH`` fits ``rise = a + b * pixels`` through the measured sizes of each model
(use the same width, e.g. 1920xN, so row-banded models see the same band shape as at 1080p) and
prints the rise and peak at that size; inputs scale exactly with pixels.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

GB = 1 << 30


def _rss_bytes(field: str) -> int:
    from mcdenoise.bench.memory import status_kib

    return status_kib(field) * 1024


def child(args: argparse.Namespace) -> None:
    """Run one model once and print one JSON line."""
    import torch

    from mcdenoise.models.registry import build_model, synthetic_batch

    torch.set_num_threads(args.threads)
    w, h = (int(v) for v in args.size[0].split("x"))
    overrides = {}
    for kv in args.set or []:
        key, _, val = kv.partition("=")
        overrides[key] = json.loads(val)
    model = build_model(args.models[0], args.preset, **overrides).to(args.device)
    model.train(args.train)
    batch = synthetic_batch(model, spp=args.spp, height=h, width=w)
    batch = {k: v.to(args.device) for k, v in batch.items()}
    inputs = sum(v.numel() * v.element_size() for v in batch.values())
    cuda = args.device.startswith("cuda")
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        before = torch.cuda.memory_allocated()
    else:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # resets VmHWM to the current resident set
        before = _rss_bytes("VmRSS")
    t0 = time.perf_counter()
    if args.train:
        model(batch).square().mean().backward()
    else:
        with torch.no_grad():
            model(batch)
    if cuda:
        torch.cuda.synchronize()
    secs = time.perf_counter() - t0
    peak = torch.cuda.max_memory_allocated() if cuda else _rss_bytes("VmHWM")
    print(json.dumps({"model": args.models[0], "preset": args.preset, "size": args.size[0], "spp": args.spp,
                      "pixels": w * h, "inputs": inputs, "rise": peak - before, "seconds": secs}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="*", help="registered model names (default: all)")
    ap.add_argument("--preset", default="small")
    ap.add_argument("--size", nargs="+", default=["256x256"], help="WxH, one or more")
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--train", action="store_true", help="forward + backward (default: inference)")
    ap.add_argument("--set", nargs="*", metavar="FIELD=JSON",
                    help="config overrides, e.g. kernel_budget_mb=16 (values parsed as JSON)")
    ap.add_argument("--extrapolate", help="WxH to extrapolate each model's peak to (needs 2+ sizes)")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per run")
    ap.add_argument("--json", help="also write all results to this file")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    if not args.models:
        from mcdenoise.models.registry import list_models

        args.models = [e.name for e in list_models()]
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
    results = []
    print(f"| model | preset | size | spp | inputs GB | rise GB | peak GB | s |")
    print(f"|---|---|---|---|---|---|---|---|")
    for name in args.models:
        runs = []
        for size in args.size:
            cmd = [sys.executable, __file__, "--child", "--models", name, "--preset", args.preset, "--size", size,
                   "--spp", str(args.spp), "--device", args.device, "--threads", str(args.threads)]
            if args.train:
                cmd.append("--train")
            if args.set:
                cmd += ["--set", *args.set]
            try:
                p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
            except subprocess.TimeoutExpired:
                print(f"| {name} | {args.preset} | {size} | {args.spp} | timeout | | | |", flush=True)
                continue
            if p.returncode != 0:
                err = (p.stderr.strip().splitlines() or ["?"])[-1]
                print(f"| {name} | {args.preset} | {size} | {args.spp} | failed: {err} | | | |", flush=True)
                continue
            r = json.loads(p.stdout.strip().splitlines()[-1])
            runs.append(r)
            results.append(r)
            print(f"| {name} | {args.preset} | {size} | {args.spp} | {r['inputs'] / GB:.3f} | {r['rise'] / GB:.3f} | "
                  f"{(r['inputs'] + r['rise']) / GB:.3f} | {r['seconds']:.1f} |", flush=True)
        if args.extrapolate and len(runs) >= 2:
            w, h = (int(v) for v in args.extrapolate.split("x"))
            px = [r["pixels"] for r in runs]
            rise = [r["rise"] for r in runs]
            n = len(px)
            mx, my = sum(px) / n, sum(rise) / n
            b = sum((x - mx) * (y - my) for x, y in zip(px, rise)) / max(1e-9, sum((x - mx) ** 2 for x in px))
            a = my - b * mx
            est_rise = a + b * w * h
            est_inputs = runs[-1]["inputs"] / runs[-1]["pixels"] * w * h
            results.append({"model": name, "preset": args.preset, "size": args.extrapolate, "spp": args.spp,
                            "extrapolated": True, "inputs": est_inputs, "rise": est_rise})
            print(f"| {name} | {args.preset} | {args.extrapolate} (extrapolated) | {args.spp} | {est_inputs / GB:.3f} | "
                  f"{est_rise / GB:.3f} | {(est_inputs + est_rise) / GB:.3f} | |", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
