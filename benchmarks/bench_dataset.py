"""Time of `mcdenoise dataset` per image, and its ratio to the built-in cornell-box at the same settings.

    .venv/bin/python benchmarks/bench_dataset.py                               # 2 scenes x 8 views, 64x64, 8 / 256 spp
    .venv/bin/python benchmarks/bench_dataset.py --count 3 --views 1 --size 128 --ref-spp 1024 --json out.json

In one process: renders ``cornell-box`` ``--cornell`` times exactly as ``mcdenoise render`` does
(scene load + ``render_image``), then ``--count`` procedural scenes with ``--views`` views each
exactly as ``mcdenoise dataset`` does, and prints the wall time per image of both and their ratio
(the issue's target: at most 3 at 64x64, 8 spp, 256-spp reference). The cornell figure is the
median of its renders after the first (the first compiles its kernels; ``mcdenoise render`` runs
later find them in Dr.Jit's disk cache), rendered ``--cornell`` times before and again after the
dataset, so that a machine load that changes during the run weighs on both sides; the
procedural figure is the whole dataset's wall time divided by its images, compilation included.

Dr.Jit caches compiled kernels on disk (``~/.drjit``): rerunning the same seeds would be faster than
a new dataset. ``--cold`` (default) points ``DRJIT_CACHE_DIR`` at a fresh temporary folder, so every
kernel compiles as it would for seeds never rendered before; ``--warm`` keeps the user's cache.

Per image the table lists, from each meta.json: ``generate`` (drawing, scene load, and the preview
check, which compiles the input's kernel), ``check`` (an extra view's camera check), ``samples`` and
``reference`` (renderer timings; a scene's first reference compiles its kernel). Under generator 4
a view's ``samples`` and ``reference`` are its shares of its view stack's renders plus its own writing.

``--rr-depth R`` starts Russian roulette at depth R in the procedural renders only (``mcdenoise
dataset --rr-depth R``; the cornell box keeps Mitsuba's 5); the line ``input noise`` then shows what the shorter expected paths cost in
noise at the same spp (docs/DATASETS.md, "Russian roulette").

To measure an older checkout, copy this file into its ``benchmarks/`` and run it there with
``--views 1`` (older DatasetConfigs have no views).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=2, help="procedural scenes (default 2)")
    ap.add_argument("--views", type=int, default=8, help="views per scene (default 8)")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--seed", type=int, default=20261123)
    ap.add_argument("--objects", default="10-50")
    ap.add_argument("--world", default="classic", help="procedural world (classic or rich)")
    ap.add_argument("--max-depth", type=int, default=6, help="path depth of both sides (default 6)")
    ap.add_argument("--rr-depth", type=int, default=5,
                    help="Russian roulette from this depth in the procedural renders only, as `mcdenoise dataset "
                         "--rr-depth` (default 5; the cornell box keeps 5)")
    ap.add_argument("--generator", type=int, default=None, help="scene pipeline version (default: the latest)")
    ap.add_argument("--cornell", type=int, default=3, help="cornell-box renders (default 3; the first is not counted)")
    cache = ap.add_mutually_exclusive_group()
    cache.add_argument("--cold", dest="cold", action="store_true", default=True, help="fresh kernel cache (default)")
    cache.add_argument("--warm", dest="cold", action="store_false", help="keep the user's kernel cache")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    tmp = tempfile.TemporaryDirectory(prefix="bench_dataset_")
    if args.cold:  # before the first Dr.Jit import
        os.environ["DRJIT_CACHE_DIR"] = str(Path(tmp.name) / "drjit-cache")

    from mcdenoise.cli.dataset import parse_objects
    from mcdenoise.data.format import read_image
    from mcdenoise.render import RenderSettings, load_scene, render_image
    from mcdenoise.render.procedural_dataset import DatasetConfig, image_paths, render_dataset

    n = args.size
    cornell: list[float] = []

    def render_cornell(times: int) -> None:
        for _ in range(times):
            t0 = time.perf_counter()
            scene = load_scene("cornell-box", width=n, height=n)
            render_image(scene, Path(tmp.name) / f"cornell_{len(cornell)}",
                         RenderSettings(spp=args.spp, ref_spp=args.ref_spp, width=n, height=n, max_depth=args.max_depth))
            cornell.append(time.perf_counter() - t0)
            del scene

    render_cornell(max(2, args.cornell))

    kw = {"views": args.views} if args.views != 1 else {}
    if args.generator is not None:
        kw["generator"] = args.generator
    cfg = DatasetConfig(count=args.count, seed=args.seed, spp=args.spp, ref_spp=args.ref_spp, width=n, height=n,
                        objects=parse_objects(args.objects), world=args.world, max_depth=args.max_depth,
                        rr_depth=args.rr_depth, **kw)
    root = Path(tmp.name) / "ds"
    t0, c0 = time.perf_counter(), time.process_time()
    render_dataset(root, cfg, progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    render_cornell(max(1, args.cornell - 1))
    cornell_s = statistics.median(cornell[1:])
    rows = []
    noise = []  # per image: mean over pixels of Var(mean) / (mean^2 + 0.01), the noisy input's expected relMSE
    for i in range(cfg.count):
        for rel in image_paths(cfg, i):
            img = read_image(root / rel)
            meta = img.meta
            px = img.read_noisy(["radiance", "radiance_variance"])
            noise.append(float((px["radiance_variance"] / (px["radiance"].astype("float64") ** 2 + 0.01)).mean()))
            proc = meta.extra["procedural"]
            rs = meta.extra.get("render_seconds", {})
            view = meta.extra.get("view", {})
            stack = meta.extra.get("view_stack")
            if stack:  # generator 4: the inputs of a stack of views came from one render, shared out evenly
                k = stack["views"][1] - stack["views"][0]
                rs = {**rs, "samples": round(rs["samples"] + stack["seconds"] / k, 3),
                      "reference": round(rs["reference"] + stack.get("reference_seconds", 0.0) / k, 3)}
            rows.append({
                "image": rel, "kind": proc["kind"], "objects": proc["objects"] + proc["furniture"],
                "rejected": len(proc.get("rejected", [])) + len(view.get("rejected_cameras", [])),
                "generate_s": proc["generate_seconds"] if view.get("index", 0) == 0 else 0.0,
                "check_s": view.get("check_seconds", 0.0), "samples_s": rs.get("samples"), "reference_s": rs.get("reference"),
                "moving": len(meta.extra.get("object_motion", {})),
                "ref_slices": meta.extra.get("ref_time_slices", 0),
            })
    tmp.cleanup()
    per_image = wall / max(1, len(rows))
    res = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}",
        "config": {"count": cfg.count, "views": args.views, "size": n, "spp": cfg.spp, "ref_spp": cfg.ref_spp,
                   "seed": cfg.seed, "objects": list(cfg.objects), "world": cfg.world, "max_depth": cfg.max_depth, "rr_depth": cfg.rr_depth, "generator": cfg.generator, "kernel_cache": "cold" if args.cold else "warm"},
        "cornell_s": [round(c, 2) for c in cornell],
        "cornell_per_image_s": round(cornell_s, 2),
        "wall_s": round(wall, 2),
        "per_image_s": round(per_image, 2),
        "cpu_s": round(cpu, 1),  # all threads of the process (Dr.Jit's pool included)
        "cpu_per_image_s": round(cpu / max(1, len(rows)), 2),
        "ratio": round(per_image / cornell_s, 2),
        "input_noise_median": round(statistics.median(noise), 5),
        "images": rows,
    }
    # Views of scenes with moving objects pay a scene update and a kernel launch per time slice:
    # their per-view cost is reported apart (first views excluded: they carry the compilations).
    for label, sel in (("moving objects", lambda r: r["moving"] > 0), ("static", lambda r: r["moving"] == 0)):
        later = [r["check_s"] + (r["samples_s"] or 0.0) + (r["reference_s"] or 0.0) for r in rows
                 if sel(r) and r["generate_s"] == 0.0]
        res[f"later_view_s_{label.split()[0]}"] = round(statistics.median(later), 3) if later else None
    print("| image | kind | objects | moving | ref slices | rejected | generate s | check s | samples s | reference s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['image']} | {r['kind']} | {r['objects']} | {r['moving']} | {r['ref_slices']} | {r['rejected']} "
              f"| {r['generate_s']:.1f} | {r['check_s']:.2f} | {r['samples_s']} | {r['reference_s']} |")
    for key in ("moving", "static"):
        v = res[f"later_view_s_{key}"]
        if v is not None:
            print(f"median check + samples + reference of a later view ({key}): {v:.2f} s "
                  f"({v / cornell_s:.2f} x cornell-box)")
    print(f"\ncornell-box {n}x{n}, {args.spp} spp + {args.ref_spp} spp reference: {', '.join(f'{c:.2f}' for c in cornell)} s "
          f"(before and after the dataset; the first compiles; median of the rest {cornell_s:.2f} s)")
    print(f"procedural: {cfg.count} scene(s) x {args.views} view(s): {wall:.1f} s wall, {per_image:.2f} s per image "
          f"({'cold' if args.cold else 'warm'} kernel cache; {res['machine']})")
    print(f"ratio procedural / cornell-box per image: {res['ratio']:.2f}")
    print(f"input noise: median over images of the {args.spp}-spp mean's Var / (mean^2 + 0.01), averaged over pixels: "
          f"{res['input_noise_median']:.4g} (the noisy input's expected relMSE; compares --rr-depth settings)")
    print(f"CPU time of the procedural images: {cpu:.1f} CPU-s, {res['cpu_per_image_s']:.2f} CPU-s per image "
          f"({res['cpu_per_image_s'] * 2000 / 3600:.2f} CPU-hours for 2000 such images)")
    if args.json:
        args.json.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
