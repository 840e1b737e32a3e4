"""Probe: does a material palette (objects sharing a few materials) make rich scenes cheaper?

    .venv/bin/python benchmarks/bench_palette.py 0    # materials as drawn (one per object)
    .venv/bin/python benchmarks/bench_palette.py 6    # the first 6 drawn, then objects pick among them

Six rich scenes (seeds 11-16, 20-40 objects, static) at 128x128, 16 spp, fresh kernel cache: the
load + first render (compilation) and the median of three later renders. Not a generator option:
docs/DATASETS.md ("Speed") gives the figures and why it was not adopted.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

os.environ["DRJIT_CACHE_DIR"] = tempfile.mkdtemp(prefix="bench_palette_")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np  # noqa: E402


def main() -> None:
    palette = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    import mcdenoise.render.procedural.objects as ob
    from mcdenoise.render.api import RenderSettings, render_samples
    from mcdenoise.render.procedural import views as pv
    from mcdenoise.render.procedural.draw import _draw
    from mcdenoise.render.procedural.loading import load_procedural

    drawn: list[dict] = []
    material = ob._material

    def shared(rng, used, textures, kind=None):  # type: ignore[no-untyped-def]
        m = material(rng, used, textures, kind)  # drawn as before: the scene's random stream is unchanged
        if len(drawn) < palette:
            drawn.append(m)
            return m
        return drawn[int(rng.integers(palette))]

    if palette > 0:
        ob._material = shared
    res = []
    for seed in (11, 12, 13, 14, 15, 16):
        drawn.clear()
        ps = _draw(seed, None, 128, 128, (20, 40), "rich")
        ps.object_motion = {}
        t0 = time.perf_counter()
        scene = load_procedural(ps, 128, 128)
        pv.set_camera(scene, ps.camera_to_world)
        st = RenderSettings(spp=16, ref_spp=0, width=128, height=128, max_depth=8, seed=1)
        render_samples(scene, st)
        first = time.perf_counter() - t0
        later = []
        for _ in range(3):
            t = time.perf_counter()
            render_samples(scene, st)
            later.append(time.perf_counter() - t)
        res.append((first, sorted(later)[1]))
        print(f"seed {seed}, palette {palette}: load + first render {first:.2f} s, later render median {sorted(later)[1]:.3f} s", flush=True)
        del scene
    mean = np.mean(res, axis=0)
    print(f"mean: load + first render {mean[0]:.2f} s, later render {mean[1]:.3f} s ({os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")


if __name__ == "__main__":
    main()
