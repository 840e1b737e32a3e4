"""Time of `mcdenoise dataset` per image: drawing + preview check, per-sample input, reference.

    .venv/bin/python benchmarks/bench_dataset.py                      # 2 images, 128x128, 8 / 1024 spp
    .venv/bin/python benchmarks/bench_dataset.py --count 4 --size 64 --ref-spp 256 --json out.json

Renders ``--count`` procedural images into a temporary folder in this process, exactly as
``mcdenoise dataset`` does, and reports the wall time per image and its parts as recorded in
each image's meta.json: ``generate`` (draw the scene, render the low-resolution preview check,
including its JIT compilation and any rejected drawings), ``load`` (Mitsuba scene load),
``samples`` and ``reference`` (the renderer's own timings, JIT compilation included).

Every new scene compiles new kernels (Mitsuba bakes material constants into them), and Dr.Jit
caches compiled kernels on disk (~/.drjit): a rerun with the same ``--seed`` is faster than the
first. Use a seed not rendered before to measure cold compilation.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mcdenoise.data.format import read_image  # noqa: E402
from mcdenoise.render.procedural_dataset import DatasetConfig, image_paths, render_dataset  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=2)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=20261121)
    ap.add_argument("--objects", default="10-50")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    lo, _, hi = args.objects.partition("-")
    cfg = DatasetConfig(count=args.count, seed=args.seed, spp=args.spp, ref_spp=args.ref_spp,
                        width=args.size, height=args.size, objects=(int(lo), int(hi or lo)))
    with tempfile.TemporaryDirectory(prefix="bench_dataset_") as tmp:
        root = Path(tmp) / "ds"
        t0 = time.perf_counter()
        render_dataset(root, cfg, progress=False)
        wall = time.perf_counter() - t0
        rows = []
        for i in range(cfg.count):
            for rel in image_paths(cfg, i):
                meta = read_image(root / rel).meta
                proc = meta.extra["procedural"]
                rs = meta.extra.get("render_seconds", {})
                rows.append({
                    "image": rel, "kind": proc["kind"], "objects": proc["objects"] + proc["furniture"],
                    "rejected": len(proc.get("rejected", [])), "generate_s": proc["generate_seconds"],
                    "load_s": proc["load_seconds"], "samples_s": rs.get("samples"), "reference_s": rs.get("reference"),
                })
    res = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}",
        "config": {"count": cfg.count, "size": args.size, "spp": cfg.spp, "ref_spp": cfg.ref_spp, "seed": cfg.seed,
                   "objects": list(cfg.objects)},
        "wall_s": round(wall, 2),
        "per_image_s": round(wall / max(1, len(rows)), 2),
        "images": rows,
    }
    print(f"| image | kind | objects | rejected | generate s | load s | samples s | reference s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['image']} | {r['kind']} | {r['objects']} | {r['rejected']} | {r['generate_s']:.1f} | {r['load_s']:.2f} "
              f"| {r['samples_s']} | {r['reference_s']} |")
    print(f"\n{cfg.count} image(s) {args.size}x{args.size}, {cfg.spp} spp + {cfg.ref_spp} spp reference: "
          f"{wall:.1f} s wall, {res['per_image_s']} s per image ({res['machine']})")
    if args.json:
        args.json.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
