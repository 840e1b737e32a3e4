"""Speed and memory of the kernel operators, fast path vs reference (prints a Markdown report).

    .venv/bin/python benchmarks/bench_ops.py                 # training-size cases, CPU
    .venv/bin/python benchmarks/bench_ops.py --full-hd       # + 1080p gather K=21 and 1080p 32 spp splat K=21
    .venv/bin/python benchmarks/bench_ops.py --device cuda   # on a GPU (memory from the CUDA allocator)
    .venv/bin/python benchmarks/bench_ops.py --json out.json # also write the numbers
    .venv/bin/python benchmarks/bench_ops.py --threads 1     # one intra-op thread (stable on a busy machine)

Times are medians of ``--repeats`` runs after one warm-up, forward alone and forward + backward
(gradients w.r.t. every input).  Memory on CPU is the rise of the process's peak resident set
(VmHWM, reset through /proc/self/clear_refs) above the resident set before the call, with the
inputs already allocated: it counts the outputs, temporaries and whatever autograd keeps.  The
script re-executes itself with ``MALLOC_MMAP_THRESHOLD_=65536`` so that glibc returns every large
block to the system when freed (otherwise freed blocks are reused silently and the rise reads 0).  On CUDA
it is ``torch.cuda.max_memory_allocated`` above the allocation before the call.

The 1080p 32 spp splat cannot hold all samples' kernels (117 GB of float32 at K = 21), so it
runs the way a model has to: one sample's kernels at a time fed to
:class:`mcdenoise.ops.SplatAccumulator`; its memory figure includes that one sample's kernels
(3.6 GB) and the accumulators, not the 32 spp values (an input, 0.8 GB).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mcdenoise.ops import (  # noqa: E402
    SplatAccumulator,
    exp_kernel,
    fused_importance_filter,
    gather,
    hierarchical_filter,
    softmax_kernel,
    splat,
)

from mcdenoise.bench.memory import status_kib  # noqa: E402

MB = 1024.0 * 1024.0


def peak_extra_mb(fn: Callable[[], object], device: torch.device) -> float:
    """Peak memory above the current level while ``fn`` runs (its result is dropped afterwards)."""
    gc.collect()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        base = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        out = fn()
        torch.cuda.synchronize(device)
        peak = torch.cuda.max_memory_allocated(device)
        del out
        return (peak - base) / MB
    base = status_kib("VmRSS")
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current RSS
    out = fn()
    peak = status_kib("VmHWM")
    del out
    gc.collect()
    return (peak - base) / 1024.0


def median_s(fn: Callable[[], object], repeats: int, device: torch.device) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _fwd_bwd(op: Callable[..., object], inputs: list[torch.Tensor]) -> Callable[[], None]:
    def run() -> None:
        for t in inputs:
            t.grad = None
        out = op(*inputs)
        outs = out if isinstance(out, tuple) else (out,)
        sum(o.sum() for o in outs).backward()  # type: ignore[union-attr]

    return run


def case(name: str, make: Callable[[], list[torch.Tensor]], op_of_impl: Callable[[str], Callable[..., object]],
         impls: tuple[str, ...], repeats: int, device: torch.device, rows: list[dict]) -> None:
    inputs = make()
    for impl in impls:
        op = op_of_impl(impl)
        with torch.no_grad():
            fwd = median_s(lambda: op(*inputs), repeats, device)
        leaf = [t.detach().clone().requires_grad_() for t in inputs]
        fb = median_s(_fwd_bwd(op, leaf), repeats, device)
        with torch.no_grad():
            mem_f = peak_extra_mb(lambda: op(*inputs), device)
        for t in leaf:
            t.grad = None  # the gradients of the timing runs would otherwise hide in the baseline
        mem_fb = peak_extra_mb(_fwd_bwd(op, leaf), device)
        row = dict(case=name, impl=impl, fwd_s=fwd, fwd_bwd_s=fb, fwd_mb=mem_f, fwd_bwd_mb=mem_fb)
        rows.append(row)
        print(f"| {name} | {impl} | {fwd * 1e3:.1f} | {fb * 1e3:.1f} | {mem_f:.1f} | {mem_fb:.1f} |", flush=True)
        del leaf
        gc.collect()


def _reexec_with_fixed_mmap_threshold() -> None:
    if os.environ.get("MALLOC_MMAP_THRESHOLD_") is None and sys.platform.startswith("linux"):
        env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
        os.execve(sys.executable, [sys.executable, *sys.argv], env)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=0, help="torch intra-op threads (0: torch's default)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--full-hd", action="store_true", help="also run the 1080p cases (several GB, minutes on CPU)")
    p.add_argument("--skip-small", action="store_true", help="only the 1080p cases")
    p.add_argument("--json", type=Path, help="write the measured rows here")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    gen = torch.Generator().manual_seed(0)

    def rnd(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen).to(dev)

    print(f"# bench_ops: torch {torch.__version__}, device {dev}, threads {torch.get_num_threads()}, "
          f"{platform.machine()} {os.cpu_count()} cpus, load {os.getloadavg()[0]:.1f}\n")
    rows: list[dict] = []
    both = ("fast", "reference")
    if not args.skip_small:
        print("| case | impl | forward ms | fwd+bwd ms | forward extra MB | fwd+bwd extra MB |")
        print("|---|---|---|---|---|---|")
        for hw in (64, 128):
            case(f"gather K=21 B=1 C=3 {hw}x{hw}",
                 lambda hw=hw: [rnd(1, 3, hw, hw), softmax_kernel(rnd(1, 441, hw, hw))],
                 lambda impl: (lambda x, w: gather(x, w, impl=impl)), both, args.repeats, dev, rows)
        for hw in (32, 64):
            case(f"splat K=21 B=1 S=8 C=3 {hw}x{hw}",
                 lambda hw=hw: [rnd(1, 8, 3, hw, hw), exp_kernel(rnd(1, 8, 441, hw, hw))],
                 lambda impl: (lambda v, w: splat(v, w, impl=impl)), both, args.repeats, dev, rows)
        case("fused importance sizes 3..13 B=1 C=3 256x256",
             lambda: [rnd(1, 3, 256, 256), rnd(1, 6, 256, 256), rnd(1, 6, 256, 256)],
             lambda impl: (lambda x, i, f: fused_importance_filter(x, i, f, impl=impl)), both, args.repeats, dev, rows)
        case("hierarchical 3 levels 5x5 gather B=1 C=3 256x256",
             lambda: [rnd(1, 3, 256, 256), rnd(1, 25, 256, 256), rnd(1, 25, 128, 128), rnd(1, 25, 64, 64), rnd(3)],
             lambda impl: (lambda x, a, b, c, lam: hierarchical_filter(x, [a, b, c], lam, impl=impl)),
             both, args.repeats, dev, rows)
    if args.full_hd:
        h, w = 1080, 1920
        print("\n| 1080p case | impl | forward s | peak extra MB |")
        print("|---|---|---|---|")
        x = rnd(1, 3, h, w)
        wts = torch.rand(1, 441, h, w, generator=gen).to(dev)
        with torch.no_grad():
            t = median_s(lambda: gather(x, wts, impl="fast"), 1, dev)
            mem = peak_extra_mb(lambda: gather(x, wts, impl="fast"), dev)
        rows.append(dict(case="gather 1080p K=21 C=3", impl="fast", fwd_s=t, fwd_mb=mem))
        print(f"| gather K=21 C=3 1920x1080 (weights 3.6 GB given) | fast | {t:.1f} | {mem:.0f} |", flush=True)
        del wts
        gc.collect()
        spp = 32
        values = rnd(1, spp, 3, h, w)

        splat_s = [0.0]

        def splat_hd() -> torch.Tensor:
            acc = SplatAccumulator()
            # Stand-in for a kernel predictor: one sample's (1, 1, 441, H, W) kernels exist at a
            # time.  The same buffer serves every sample (the op's cost does not depend on the
            # values), so the time below is the splatting alone, without kernel generation.
            k_s = torch.rand(1, 1, 441, h, w, generator=gen).to(dev)
            for s in range(spp):
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                t0 = time.perf_counter()
                acc.add(values[:, s : s + 1], k_s)
                if dev.type == "cuda":
                    torch.cuda.synchronize(dev)
                splat_s[0] += time.perf_counter() - t0
            return acc.normalized()

        with torch.no_grad():
            mem = peak_extra_mb(splat_hd, dev)
        t = splat_s[0]
        rows.append(dict(case="splat 1080p 32spp K=21 C=3 (accumulator, one sample's kernels at a time)",
                         impl="fast", fwd_s=t, fwd_mb=mem))
        print(f"| splat K=21 32 spp C=3 1920x1080, one sample's kernels at a time | fast | {t:.1f} | {mem:.0f} |",
              flush=True)
    if args.json:
        tmp = args.json.with_name(args.json.name + ".tmp")
        tmp.write_text(json.dumps(dict(device=str(dev), torch=torch.__version__, rows=rows), indent=1))
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    _reexec_with_fixed_mmap_threshold()
    raise SystemExit(main())
