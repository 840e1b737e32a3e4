"""Could procedural scenes share one compiled kernel? Compile time per scene and callables shared.

    .venv/bin/python benchmarks/kernel_sharing.py [--count 2] [--world detailed] [--seed 7]

Renders ``--count`` procedural scenes (one view each, 128x128, 16 spp, no reference) with a fresh
Dr.Jit kernel cache, Dr.Jit's kernel history and its IR printing on. Prints, for every distinct
large kernel (the path tracer's), its operation count and LLVM compile time, then the callables
(``define ... @func_<hash>``: a BSDF's, a shape's or an emitter's code, deduplicated by Dr.Jit
when identical) of each, and how many of them the other scenes' kernels have too. A scene whose
callables all occur in an earlier kernel would still compile again unless the whole kernel is
identical; the figure says how far the generator's scenes are from that (docs/DATASETS.md).
"""

from __future__ import annotations

import argparse
import atexit
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=2)
    ap.add_argument("--world", default="detailed")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--objects", default="10-40")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="kernel_sharing_"))
    atexit.register(shutil.rmtree, tmp, True)  # the kernel cache, the renders (and the IR log: ~70 MB)
    os.environ["DRJIT_CACHE_DIR"] = str(tmp / "drjit-cache")  # before the first Dr.Jit import

    import drjit as dr

    from mcdenoise.cli.dataset import parse_objects
    from mcdenoise.render.procedural_dataset import DatasetConfig, render_dataset

    cfg = DatasetConfig(count=a.count, seed=a.seed, spp=16, ref_spp=0, width=128, height=128,
                        objects=parse_objects(a.objects), world=a.world, max_depth=8)
    log = tmp / "ir.txt"
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.set_flag(dr.JitFlag.PrintIR, True)
    sys.stdout.flush()
    saved = os.dup(1)
    with open(log, "w") as f:  # Dr.Jit prints the IR to the process's standard output
        os.dup2(f.fileno(), 1)
        try:
            render_dataset(tmp / "ds", cfg, progress=False)
        finally:
            os.dup2(saved, 1)
    dr.set_flag(dr.JitFlag.PrintIR, False)
    history = [e for e in dr.kernel_history() if e.get("operation_count", 0) > 2000]

    lines = log.read_text(errors="replace").split("\n")
    starts = [i for i, line in enumerate(lines) if line.startswith("define void @drjit_")] + [len(lines)]
    kernels: dict[str, set[str]] = {}
    for s, e in zip(starts, starts[1:]):
        h = lines[s].split("@drjit_")[1][:32]
        if e - s > 5000 and h not in kernels:
            body = "\n".join(lines[s:e])
            kernels[h] = set(re.findall(r"^define [^\n]*?@(func_[0-9a-f]+)", body, flags=re.M))
    print(f"{a.count} scene(s), world {a.world}, seed {a.seed}: {len(kernels)} distinct path-tracer kernel(s)")
    for e in history:
        if not e.get("cache_hit"):
            print(f"  kernel {e['hash'][:12]}: {e['operation_count']} ops, codegen {e['codegen_time']:.0f} ms, "
                  f"LLVM compile {e['backend_time']:.0f} ms")
    seen: set[str] = set()
    for h, funcs in kernels.items():
        print(f"  kernel {h[:12]}: {len(funcs)} callables, {len(funcs & seen)} of them in an earlier kernel")
        seen |= funcs


if __name__ == "__main__":
    main()
