"""Where `mcdenoise dataset`'s time goes: cProfile of one procedural dataset render, fresh kernel cache.

    .venv/bin/python benchmarks/profile_dataset.py --world rich --views 16     # 2 scenes, 128x128, 16 spp
    .venv/bin/python benchmarks/profile_dataset.py --cornell 10               # the built-in cornell box

Prints the wall and CPU time, then the functions by cumulative and by own time. The own time of
a function that calls Dr.Jit includes the Dr.Jit work (nanobind functions are not profiled as
built-ins), and ``numpy.asarray`` on a Dr.Jit array waits for the kernel it reads. The figures of
docs/DATASETS.md "Where a 128x128 image's time goes now" and "One kernel for every scene?" came
from this script. ``--cornell N`` profiles N renders of the built-in cornell box instead (same size
and spp, as ``benchmarks/bench_dataset.py`` renders it), after one unprofiled render that compiles.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="rich")
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--count", type=int, default=2)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--rr-depth", type=int, default=5, help="Russian roulette depth of the procedural renders")
    ap.add_argument("--cornell", type=int, default=0, help="profile this many cornell-box renders instead")
    ap.add_argument("--warm", action="store_true",
                    help="keep the user's kernel cache (run twice: the second run has no compilation)")
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="profile_dataset_")
    if not a.warm:  # before the first Dr.Jit import
        os.environ["DRJIT_CACHE_DIR"] = str(Path(tmp) / "drjit-cache")

    from mcdenoise.render import RenderSettings, load_scene, render_image
    from mcdenoise.render.procedural_dataset import DatasetConfig, render_dataset

    def cornell(i: int) -> None:
        settings = RenderSettings(spp=a.spp, ref_spp=0, width=a.size, height=a.size, max_depth=8)
        render_image(load_scene("cornell-box", width=a.size, height=a.size), Path(tmp) / f"cornell_{i}", settings)

    def work() -> None:
        if a.cornell:
            for i in range(1, a.cornell + 1):
                cornell(i)
        else:
            cfg = DatasetConfig(count=a.count, seed=a.seed, spp=a.spp, ref_spp=0, width=a.size, height=a.size,
                                objects=(10, 40), world=a.world, max_depth=8, views=a.views,
                                rr_depth=a.rr_depth)
            render_dataset(Path(tmp) / "ds", cfg, progress=False)

    if a.cornell:
        cornell(0)  # compiles; not profiled
    prof = cProfile.Profile()
    t0, c0 = time.perf_counter(), time.process_time()
    prof.enable()
    work()
    prof.disable()
    what = f"{a.cornell} cornell-box render(s)" if a.cornell else f"{a.count} scene(s) x {a.views} view(s)"
    print(f"wall {time.perf_counter() - t0:.1f} s, CPU {time.process_time() - c0:.1f} s, {what}")
    stats = pstats.Stats(prof)
    stats.sort_stats("cumulative").print_stats(a.top)
    stats.sort_stats("tottime").print_stats(a.top)


if __name__ == "__main__":
    main()
