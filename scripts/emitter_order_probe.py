"""Mitsuba's emitter order across loads, and what it does to pixels (campaign 28, docs/TRAINING.md).

For each scene file: how many distinct emitter orders Mitsuba lists over ``--loads`` loads (with
``parallel`` loading on and off), whether the renderer applies its canonical order, and two renders
of the same seed from two loads, once with Mitsuba's order (the renderer with its canonical order
switched off) and once with the renderer's: the share of pixels that differ.

    python scripts/emitter_order_probe.py ../shared/valscenes/{kitchen,spaceship,coffee}/scene.xml
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import mcdenoise.render.prepare as prepare
from mcdenoise.render import RenderSettings, load_scene, render_samples
from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.emitter_order import emitter_order


def orders(mi, path: Path, loads: int, parallel: bool) -> int:
    seen = set()
    for _ in range(loads):
        scene = mi.load_file(str(path), parallel=parallel)
        seen.add(tuple(f"{e.class_name()}:{e.bbox()}" for e in scene.emitters()))
    return len(seen)


def differing(a: np.ndarray, b: np.ndarray) -> float:
    """Share of pixels of ``(3, H, W)`` images that differ in any channel."""
    return float(np.mean(np.any(a != b, axis=0)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--loads", type=int, default=8)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--max-depth", type=int, default=8)
    a = ap.parse_args()
    mi = mitsuba()
    for path in a.scenes:
        n_par, n_seq = orders(mi, path, a.loads, True), orders(mi, path, a.loads, False)
        settings = RenderSettings(spp=a.spp, ref_spp=0, width=a.size, height=a.size, seed=7, max_depth=a.max_depth)
        px: dict[bool, list[np.ndarray]] = {False: [], True: []}
        for _ in range(2):
            scene = load_scene(path, width=a.size, height=a.size)
            canonical = emitter_order(mi, scene) is not None
            for ours in (False, True):
                # The renderer takes its order from prepare.emitter_order; None is Mitsuba's own.
                prepare.emitter_order = emitter_order if ours else (lambda mi, scene: None)
                px[ours].append(render_samples(scene, settings)[0]["radiance"].mean(axis=0))
        prepare.emitter_order = emitter_order
        mitsuba_px, ours_px = px[False], px[True]
        print(f"{path}: {n_par} emitter orders in {a.loads} loads (parallel), {n_seq} (parallel=False); "
              f"canonical order {'applied' if canonical else 'not needed'}; two loads, same seed, pixels that differ: "
              f"Mitsuba's order {differing(*mitsuba_px):.1%}, the renderer's {differing(*ours_px):.1%}", flush=True)


if __name__ == "__main__":
    main()
