"""Does ``torch.compile`` pay for our models' inference? Eager (the fast inference form of
``prepare_inference``) against ``torch.compile(model)`` in the same process, interleaved.

    .venv/bin/python benchmarks/bench_compile.py --models wskp:paper kpcn layer_optimized --size 960x540 --spp 8

Prints, per model: eager and compiled median ms, the compile time (first call), and the largest
difference between the two outputs relative to the image maximum. Each model runs in a child
process with ``--timeout`` seconds (a model whose compilation does not finish gets a row saying
so). Needs a C++ compiler (Inductor generates C++ on the CPU).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import _timing  # noqa: F401  (puts the repository on sys.path)
import torch

from mcdenoise.bench.plan import parse_method
from mcdenoise.bench.timing import interleaved_times
from mcdenoise.models.inference import inference_context, prepare_inference
from mcdenoise.models.registry import build_model, synthetic_batch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", nargs="+", default=["wskp:paper", "kpcn", "layer_optimized"])
    ap.add_argument("--size", default="960x540")
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--precision", default="float32", choices=("float32", "bfloat16", "auto"))
    ap.add_argument("--timeout", type=float, default=300.0, help="seconds per model, compilation included")
    ap.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    if args.one:
        _one(args.models[0], w, h, args)
        return
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {w}x{h}, {args.spp} spp, {args.precision}")
    print("| model | eager ms | compiled ms | compiled / eager | compile s | max diff / max |")
    print("|---|---:|---:|---:|---:|---:|", flush=True)
    for label in args.models:
        cmd = [sys.executable, __file__, "--one", "--models", label, "--size", args.size, "--spp", str(args.spp),
               "--rounds", str(args.rounds), "--precision", args.precision]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
            rows = [ln for ln in done.stdout.splitlines() if ln.startswith("|")]
            print(rows[-1] if rows else f"| {label} | failed: {done.stderr.strip().splitlines()[-1:]} |", flush=True)
        except subprocess.TimeoutExpired:
            print(f"| {label} | - | did not finish compiling and timing within {args.timeout:.0f} s | - | - | - |", flush=True)


def _one(label: str, w: int, h: int, args: argparse.Namespace) -> None:
    m = parse_method(label)
    torch.manual_seed(0)
    model = prepare_inference(build_model(m.name, m.preset), precision=args.precision)
    batch = synthetic_batch(model, spp=args.spp, height=h, width=w, generator=torch.Generator().manual_seed(1))
    with inference_context(True):
        ref = model(batch)
        compiled = torch.compile(model, dynamic=False)
        t0 = time.perf_counter()
        out = compiled(batch)
        compile_s = time.perf_counter() - t0
        times = interleaved_times({"eager": lambda: model(batch), "compiled": lambda: compiled(batch)}, args.rounds)
    e, c = statistics.median(times["eager"]), statistics.median(times["compiled"])
    diff = ((out - ref).abs().max() / ref.abs().max()).item()
    print(f"| {m.label} | {e * 1e3:,.0f} | {c * 1e3:,.0f} | {c / e:.2f} | {compile_s:.1f} | {diff:.1e} |", flush=True)

if __name__ == "__main__":
    main()
