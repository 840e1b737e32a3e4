"""Where a procedural dataset's Dr.Jit time goes: its kernel launches by size, from Dr.Jit's history.

    .venv/bin/python benchmarks/kernel_history.py [--count 2] [--views 16] [--warm]
    .venv/bin/python benchmarks/kernel_history.py --reload     # the cornell box loaded twice

Renders ``render_dataset`` (detailed world, 128x128, 16 spp, no reference) with the kernel history
on and prints, per band of operation counts, the launches, how many compiled, and their
compilation, code generation and execution time; then every path-tracer launch (lanes, operations,
execution ms, cache hit). The figures of docs/DATASETS.md "Where the rest goes" came from it
(``--warm``: the user's kernel cache, run twice so the second has no compilation).

``--reload`` renders the cornell box, then loads it again while the first scene is still
referenced and renders that: it prints both path-tracer kernels' operation counts and whether the
second hit the first's kernel (it does not: every live instance's code joins the virtual calls).

``--variants`` asks what a kernel shared across scenes needs: it renders the cornell box, frees it,
then renders edited copies one at a time (each freed before the next) and prints, per edit, the
path tracer's operation count and whether it hit the kernel compiled before: the same scene again,
other colours and light, moved geometry, an extra shape with an existing material, an extra
material (with values of its own, and with a present material's values), a shape of another type.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

BANDS = [(0, 100), (100, 1000), (1000, 5000), (5000, 10**9)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=2)
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--warm", action="store_true", help="keep the user's kernel cache")
    ap.add_argument("--reload", action="store_true", help="the cornell box loaded twice instead")
    ap.add_argument("--variants", action="store_true", help="edited cornell boxes, one alive at a time")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="kernel_history_"))
    if not a.warm:  # before the first Dr.Jit import
        os.environ["DRJIT_CACHE_DIR"] = str(tmp / "drjit-cache")

    import drjit as dr

    from mcdenoise.render import RenderSettings, load_scene
    from mcdenoise.render.procedural_dataset import DatasetConfig, render_dataset
    from mcdenoise.render.samples import iter_sample_chunks

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    if a.variants:
        _variants(dr, load_scene, iter_sample_chunks, RenderSettings)
        return
    if a.reload:
        settings = RenderSettings(spp=16, ref_spp=0, width=128, height=128, max_depth=8)
        alive = []
        for i in range(2):
            alive.append(load_scene("cornell-box", width=128, height=128))  # the first stays referenced
            dr.kernel_history()  # clear
            for _ in iter_sample_chunks(alive[-1], settings):
                pass
            big = max(dr.kernel_history(), key=lambda e: e.get("operation_count", 0))
            print(f"load {i + 1}: path tracer {big['operation_count']} ops, cache hit {bool(big.get('cache_hit'))}, "
                  f"compile {big.get('backend_time', 0):.0f} ms")
        return

    cfg = DatasetConfig(count=a.count, seed=a.seed, spp=16, ref_spp=0, width=128, height=128, objects=(10, 40),
                        world="detailed", max_depth=8, views=a.views)
    t0 = time.perf_counter()
    render_dataset(tmp / "ds", cfg, progress=False)
    wall = time.perf_counter() - t0
    h = dr.kernel_history()
    print(f"{a.count} scene(s) x {a.views} view(s): {wall:.1f} s wall, {len(h)} launches "
          f"({'warm' if a.warm else 'cold'} kernel cache)")
    for lo, hi in BANDS:
        g = [e for e in h if lo <= e.get("operation_count", 0) < hi]
        miss = [e for e in g if not e.get("cache_hit")]
        print(f"  {lo}-{hi} ops: {len(g)} launches, {len(miss)} compiled, compile "
              f"{sum(e.get('backend_time', 0) for e in miss) / 1000:.2f} s, codegen "
              f"{sum(e.get('codegen_time', 0) for e in g) / 1000:.2f} s, execution "
              f"{sum(e.get('execution_time', 0) for e in g) / 1000:.2f} s")
    print("path-tracer launches (lanes, operations, execution ms, cache hit):")
    for e in h:
        if e.get("operation_count", 0) >= BANDS[-1][0]:
            print(f"  {e.get('size')} {e['operation_count']} {e.get('execution_time', 0):.1f} {bool(e.get('cache_hit'))}")


def _cornell_edits() -> list[tuple[str, dict]]:
    """(label, scene dict): the cornell box and edits of it that keep or change its structure."""
    import gc

    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()  # the variant set
    base = mi.cornell_box()
    fresh = mi.cornell_box  # a new dict each call (transforms do not deep-copy)
    out = [("cornell box", base), ("the same again", fresh())]
    d = fresh()
    d["red"]["reflectance"]["value"] = [0.1, 0.2, 0.7]
    d["white"]["reflectance"]["value"] = [0.3, 0.3, 0.3]
    d["light"]["emitter"]["radiance"]["value"] = [180.0, 150.0, 100.0]
    out.append(("other colours and light", d))
    d = fresh()
    d["small-box"]["to_world"] = mi.ScalarTransform4f().translate([-0.3, -0.8, 0.2]).scale(0.2)
    d["large-box"]["to_world"] = mi.ScalarTransform4f().translate([0.4, -0.5, -0.3]).rotate([0, 1, 0], 30).scale([0.25, 0.5, 0.25])
    out.append(("moved geometry", d))
    d = fresh()
    d["third-box"] = {"type": "cube", "to_world": mi.ScalarTransform4f().translate([0, 0.5, 0]).scale(0.1),
                      "bsdf": {"type": "ref", "id": "white"}}
    out.append(("an extra shape, existing material", d))
    for label, value in (("one more diffuse, values of its own", [0.1, 0.1, 0.6]),
                         ("one more diffuse, the white's values", base["white"]["reflectance"]["value"])):
        d = fresh()
        d["extra"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": value}}
        d["small-box"]["bsdf"] = {"type": "ref", "id": "extra"}
        out.append((label, d))
    d = fresh()
    d["small-box"] = {"type": "sphere", "center": [0.3, -0.7, 0.4], "radius": 0.3, "bsdf": {"type": "ref", "id": "white"}}
    out.append(("a cube replaced by a sphere", d))
    gc.collect()
    return out


def _variants(dr, load_scene, iter_sample_chunks, RenderSettings) -> None:  # noqa: ANN001 - imported late
    import gc

    settings = RenderSettings(spp=16, ref_spp=0, width=128, height=128, max_depth=8)
    seen: dict[int, str] = {}
    for label, d in _cornell_edits():
        scene = load_scene(d, width=128, height=128)
        dr.kernel_history()  # clear
        t = time.perf_counter()
        for _ in iter_sample_chunks(scene, settings):
            pass
        wall = time.perf_counter() - t
        big = max(dr.kernel_history(), key=lambda e: e.get("operation_count", 0))
        ops = big["operation_count"]
        print(f"{label:40s} path tracer {ops} ops, cache hit {bool(big.get('cache_hit'))}, compile "
              f"{big.get('backend_time', 0):.0f} ms, render {wall:.2f} s"
              + (f" (same size as: {seen[ops]})" if ops in seen else ""))
        seen.setdefault(ops, label)
        del scene
        gc.collect()
        dr.flush_malloc_cache()


if __name__ == "__main__":
    main()
