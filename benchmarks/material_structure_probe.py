"""What would one material structure for every object buy? Compile and render time of a drawn
procedural scene as drawn, and with its materials replaced (an upper bound, not a generator).

    .venv/bin/python benchmarks/material_structure_probe.py [--seeds 7 8 9] [--world detailed]

For each seed the scene is drawn (unchecked, as the generator draws it) and rendered at 128x128,
16 spp, no reference, through the dataset's own path (``render_image``), in three versions:

- ``drawn``: as drawn;
- ``one_diffuse``: every BSDF replaced by the *same* diffuse BSDF object (one instance, one
  callable): the least a shared structure could cost;
- ``diffuse_each``: every BSDF replaced by a diffuse BSDF of its own (a constant reflectance of its
  own colour): one structure, many instances (does Dr.Jit merge them into one callable?);
- ``principled_each``: every BSDF replaced by a ``principled`` BSDF of its own (its own base colour,
  roughness, metallic and transmission values): one structure rich enough for plastics, metals
  and glass, the candidate of an uber-material generator.

Each version is loaded and rendered 3 times; printed: the scene dict's entry count, the LLVM
compile time of its new kernels (Dr.Jit's kernel history; 0 when an earlier scene's kernel was
reused), the first render (with compilation) and the median of the other two. Fresh kernel
cache per process.
"""

from __future__ import annotations

import argparse
import atexit
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

BSDF_TYPES = {"diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric",
              "roughdielectric", "thindielectric", "principled", "bumpmap", "normalmap", "twosided",
              "blendbsdf", "mask", "null"}


def _replace_bsdfs(node: Any, make: Any) -> Any:
    """``node`` with every BSDF dict (a dict whose ``type`` is a BSDF plugin) replaced by ``make(old)``."""
    if isinstance(node, dict):
        if node.get("type") in BSDF_TYPES:
            return make(node)
        return {k: _replace_bsdfs(v, make) for k, v in node.items()}
    return node


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[7, 8, 9])
    ap.add_argument("--world", default="detailed")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="material_probe_"))
    atexit.register(shutil.rmtree, tmp, True)  # the kernel cache, the renders (and the IR log: ~70 MB)
    os.environ["DRJIT_CACHE_DIR"] = str(tmp / "drjit-cache")  # before the first Dr.Jit import

    import drjit as dr
    import numpy as np

    from mcdenoise.render import RenderSettings, render_image
    from mcdenoise.render.api import load_scene
    from mcdenoise.render.procedural.draw import _draw

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    settings = RenderSettings(spp=16, ref_spp=0, width=128, height=128, max_depth=8)
    print(f"world {a.world}, 128x128, 16 spp, max depth 8; seconds per render")
    print(f"{'seed':>4} {'version':<13} {'entries':>7} {'compile s':>9} {'first':>6} {'later':>6}")
    for seed in a.seeds:
        ps = _draw(seed, None, 128, 128, (10, 40), a.world)
        shared = {"type": "diffuse", "id": "shared_bsdf", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
        rng = np.random.default_rng(seed)
        versions = {
            "drawn": ps.scene,
            "one_diffuse": {**_replace_bsdfs(ps.scene, lambda _: {"type": "ref", "id": "shared_bsdf"}), "shared_bsdf": shared},
            "diffuse_each": _replace_bsdfs(ps.scene, lambda _: {
                "type": "diffuse", "reflectance": {"type": "rgb", "value": rng.uniform(0.1, 0.8, 3).tolist()}}),
            "principled_each": _replace_bsdfs(ps.scene, lambda _: {
                "type": "principled", "base_color": {"type": "rgb", "value": rng.uniform(0.1, 0.8, 3).tolist()},
                "roughness": float(rng.uniform(0.05, 0.9)), "metallic": float(rng.uniform(0, 1)),
                "spec_trans": float(rng.uniform(0, 1))}),
        }
        for name, scene_dict in versions.items():
            dr.kernel_history()  # clear
            times = []
            for i in range(3):
                scene = load_scene(scene_dict, width=128, height=128)
                t0 = time.perf_counter()
                render_image(scene, tmp / f"{seed}_{name}_{i}", settings, camera_to_world=ps.camera_to_world)
                times.append(time.perf_counter() - t0)
                del scene
            comp = sum(e.get("backend_time", 0.0) for e in dr.kernel_history() if not e.get("cache_hit")) / 1000
            print(f"{seed:>4} {name:<13} {len(ps.scene):>7} {comp:>9.2f} {times[0]:>6.2f} {statistics.median(times[1:]):>6.2f}")


if __name__ == "__main__":
    main()
