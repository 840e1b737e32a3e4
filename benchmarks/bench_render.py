"""Renderer speed and memory, measured in one run (prints a Markdown report).

    .venv/bin/python benchmarks/bench_render.py            # all parts
    .venv/bin/python benchmarks/bench_render.py --quick    # skip the 1024x1024 memory run

Parts:
1. samples/s of our per-sample render with every feature vs ``mi.render`` with Mitsuba's built-in
   ``path`` on the same scene, size and spp (medians of repeats, same process, warm kernels);
2. a 128x128, 8 spp image folder with its 1024 spp reference, end to end in a fresh process,
   with an empty Dr.Jit kernel cache (cold: includes every compilation) and with a warm one;
3. compilation is not repeated for a new seed or a new time (kernel-cache hits + timings);
4. peak memory of a 1024x1024, 64 spp image folder (fresh process; peak RSS and peak anonymous
   memory, the latter excluding the memory-mapped sample file the kernel can write back).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from _timing import median_time  # benchmarks/ is the script's folder

REPO = Path(__file__).resolve().parent.parent
XML = REPO / "tests" / "fixtures" / "scenes" / "thinlens_textured.xml"


def part_throughput(size: int, spp: int, repeats: int) -> list[str]:
    import drjit as dr
    import numpy as np

    from mcdenoise.render import RenderSettings, load_scene, render_samples
    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    rows = [
        f"### 1. Throughput, {size}x{size} at {spp} spp (median of {repeats}, warm kernels)",
        "",
        "| scene | mi.render `path` (Msamples/s) | ours, radiance only via mi.render (Msamples/s) | ours, per-sample, all features, to numpy (Msamples/s) | ratio all-features / `path` |",
        "|---|---|---|---|---|",
    ]
    n = size * size * spp
    for name in ("cornell-box", "cornell-dof", str(XML)):
        scene = load_scene(name, width=size, height=size)
        st = RenderSettings(spp=spp, ref_spp=0, width=size, height=size, seed=1)
        path = mi.load_dict({"type": "path", "max_depth": st.max_depth})
        ours = mi.load_dict({"type": "mcdenoise_path", "max_depth": st.max_depth})
        seeds = iter(range(10**6))

        def run_path() -> None:
            np.asarray(mi.render(scene, integrator=path, spp=spp, seed=next(seeds)))

        def run_ours_film() -> None:
            np.asarray(mi.render(scene, integrator=ours, spp=spp, seed=next(seeds)))

        def run_samples() -> None:
            render_samples(scene, st, seed=next(seeds))

        for f in (run_path, run_ours_film, run_samples):  # compile once
            f()
        t_path = median_time(run_path, repeats)
        t_film = median_time(run_ours_film, repeats)
        t_smp = median_time(run_samples, repeats)
        label = Path(name).name if os.sep in name else name
        rows.append(f"| {label} | {n / t_path / 1e6:.3f} | {n / t_film / 1e6:.3f} | {n / t_smp / 1e6:.3f} | {t_path / t_smp:.2f} |")
        dr.flush_malloc_cache()
    return rows


_E2E = r"""
import sys, time, json, tempfile, os
t0 = time.perf_counter()
from mcdenoise.render import RenderSettings, load_scene, render_image
scene = load_scene("cornell-box", width=128, height=128)
st = RenderSettings(spp=8, ref_spp=1024, width=128, height=128, seed=int(sys.argv[1]))
out = render_image(scene, os.path.join(tempfile.mkdtemp(), "img"), st, scene_name="cornell-box")
meta = json.load(open(os.path.join(out, "meta.json")))
print(json.dumps({"total": time.perf_counter() - t0, **meta["extra"]["render_seconds"]}))
"""


def part_end_to_end() -> list[str]:
    rows = [
        "### 2. 128x128, 8 spp image folder + 1024 spp reference, fresh process (cornell-box)",
        "",
        "| kernel cache | total incl. import, load, compile, write (s) | per-sample part (s) | reference part (s) |",
        "|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory() as home:
        env = dict(os.environ, HOME=home)  # Dr.Jit keeps its kernel cache under ~/.drjit
        for label, seed in (("cold (empty ~/.drjit)", 1), ("warm (same cache, new seed)", 2)):
            r = subprocess.run([sys.executable, "-c", _E2E, str(seed)], env=env, capture_output=True, text=True,
                               cwd=REPO, timeout=900)
            if r.returncode != 0:
                rows.append(f"| {label} | failed: {r.stderr.strip().splitlines()[-1]} | | |")
                continue
            d = json.loads(r.stdout.strip().splitlines()[-1])
            rows.append(f"| {label} | {d['total']:.1f} | {d['samples']:.1f} | {d['reference']:.1f} |")
    return rows


def part_recompile() -> list[str]:
    import drjit as dr

    from mcdenoise.render import RenderSettings, builtin_motion, load_scene, render_samples

    rows = ["### 3. No recompilation for a new seed or time (64x64, 4 spp)", "",
            "| scene | first render (s) | new seed (s) | JIT kernels on new seed | of which cache hits |",
            "|---|---|---|---|---|"]
    for name in ("cornell-box", "cornell-motion", "cornell-camera-motion"):
        scene = load_scene(name, width=64, height=64)
        st = RenderSettings(spp=4, ref_spp=0, width=64, height=64, seed=0, **builtin_motion(name))
        t0 = time.perf_counter()
        render_samples(scene, st)
        t1 = time.perf_counter()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        render_samples(scene, st, seed=12345)  # new seed and (motion scenes) new slice times
        t2 = time.perf_counter()
        hist = [k for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT]
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        hits = sum(1 for k in hist if k.get("cache_hit"))
        rows.append(f"| {name} | {t1 - t0:.2f} | {t2 - t1:.2f} | {len(hist)} | {hits} |")
    return rows


_BIG = r"""
import sys, os, tempfile, shutil, time, json
from mcdenoise.render import RenderSettings, load_scene, render_image
scene = load_scene("cornell-box", width=1024, height=1024)
st = RenderSettings(spp=64, ref_spp=int(sys.argv[1]), width=1024, height=1024, seed=0)
d = tempfile.mkdtemp(dir=sys.argv[2])
t0 = time.perf_counter()
out = render_image(scene, os.path.join(d, "img"), st)
size = sum(p.stat().st_size for p in __import__("pathlib").Path(out).iterdir())
print(json.dumps({"seconds": time.perf_counter() - t0, "bytes": size}))
shutil.rmtree(d)
"""


def _rss_anon_kb(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("RssAnon:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def part_memory(ref_spp: int) -> list[str]:
    import resource

    rows = [f"### 4. Peak memory, 1024x1024 at 64 spp, all features, reference {ref_spp} spp (cornell-box)", ""]
    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR", "/tmp")) as tmp:
        before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        p = subprocess.Popen([sys.executable, "-c", _BIG, str(ref_spp), tmp], cwd=REPO, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
        peak_anon = 0
        stop = threading.Event()

        def poll() -> None:
            nonlocal peak_anon
            while not stop.is_set():
                peak_anon = max(peak_anon, _rss_anon_kb(p.pid))
                time.sleep(0.1)

        th = threading.Thread(target=poll, daemon=True)
        th.start()
        out, err = p.communicate(timeout=3600)
        stop.set()
        th.join()
        maxrss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        if p.returncode != 0:
            return rows + [f"failed: {err.strip().splitlines()[-1] if err.strip() else p.returncode}"]
        d = json.loads(out.strip().splitlines()[-1])
        rows += [
            "| peak RSS (GiB, incl. mapped sample-file pages) | peak anonymous memory (GiB, sampled every 0.1 s) | time (s) | folder size (GiB) |",
            "|---|---|---|---|",
            f"| {max(maxrss, before) / 2**20:.2f} | {peak_anon / 2**20:.2f} | {d['seconds']:.0f} | {d['bytes'] / 2**30:.2f} |",
        ]
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the 1024x1024 memory run")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--big-ref-spp", type=int, default=16)
    args = ap.parse_args()
    import platform

    lines = [
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {os.cpu_count()} CPU cores "
        f"({platform.processor() or platform.machine()}), load average at start "
        f"{os.getloadavg()[0]:.1f} (the machine is shared: compare ratios, not absolute figures).",
        "",
    ]
    lines += part_throughput(args.size, args.spp, args.repeats) + [""]
    lines += part_recompile() + [""]
    lines += part_end_to_end() + [""]
    if not args.quick:
        lines += part_memory(args.big_ref_spp) + [""]
    lines.append(f"Load average at end: {os.getloadavg()[0]:.1f}.")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
