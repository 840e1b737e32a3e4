"""Render one drawn Cycles scene at each input spp and as a reference, in its own process.

    python -m mcdenoise.render.cycles.worker --seed S --index I --spp 4 8 16 --ref-spp 256 \\
        --size 128 --out DIR [--threads 1]

writes ``DIR/scene.json`` (the description), ``DIR/spp<k>.exr`` for each k and ``DIR/ref.exr``,
each through a temporary name (a killed worker leaves no half file). The input renders and the
reference use different seeds (independent noise); a render's seed is fixed by (seed, index, spp).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from mcdenoise.render.cycles.draw import draw_scene

__all__ = ["render_seed", "main"]


def render_seed(seed: int, index: int, spp: int, reference: bool = False) -> int:
    """Cycles' seed for one render: distinct across scenes, spps and the reference, < 2^31."""
    return (seed * 1_000_003 + index * 7919 + spp * 2 + int(reference)) % (2 ** 31 - 1)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--index", type=int, required=True)
    p.add_argument("--spp", type=int, nargs="+", required=True)
    p.add_argument("--ref-spp", type=int, required=True)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, required=True)
    a = p.parse_args(argv)
    import bpy

    from mcdenoise.render.cycles.build import build_scene
    from mcdenoise.render.cycles.recipe import apply_recipe

    desc = draw_scene(a.seed, a.index)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "scene.json").write_text(json.dumps(desc, indent=1) + "\n")
    jobs = [(k, a.out / f"spp{k}.exr", False) for k in a.spp] + [(a.ref_spp, a.out / "ref.exr", True)]
    for spp, path, ref in jobs:
        if path.exists():
            continue
        scene = build_scene(bpy, desc)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.exr")
        write_still = apply_recipe(scene, str(tmp), spp=spp, size=a.size, seed=render_seed(a.seed, a.index, spp, ref),
                                   threads=a.threads, light_passes=True)
        bpy.ops.render.render(write_still=write_still)
        tmp.replace(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
