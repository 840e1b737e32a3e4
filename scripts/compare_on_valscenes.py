"""Two models side by side on eval reports of the third-party scenes: means, per-scene ratios to
OIDN high, how many scenes the new one improves, and where either is worse than the noisy input.
With several render seeds (``mcdenoise eval --scenes ... --render-seed 7 8 9``), also the means of
each seed and on how many seeds the new model's mean is the better one. Means print with 5 digits of
relMSE and 4 decimals of PSNR, since a shipping rule compares them and legs differ by a few mdB.

    python scripts/compare_on_valscenes.py reports/val_RUN/results.json OLD NEW [--baseline oidn-high]
    python scripts/compare_on_valscenes.py reports/new/results.json reports/old/results.json OLD NEW
    python scripts/compare_on_valscenes.py ... OLD NEW --per-scene   # + NEW / OLD per scene, over the seeds
    python scripts/compare_on_valscenes.py ... oidn-high NEW --exclude bathroom   # the means without a scene

Several reports are merged (the first one to hold an image, spp and method wins), so a model
scored alone can be compared with one scored in another run on the same inputs.
"""
from __future__ import annotations

import argparse
import collections
import json
import re

import numpy as np


def _seed(image: str, seeds: dict[str, int | None]) -> int | None:
    if image in seeds:
        return seeds[image]
    m = re.search(r"_seed(\d+)$", image)  # reports written before images carried their seed
    return int(m.group(1)) if m else None


def collect(files: list[str]) -> dict[tuple[str, int | None, int], dict[str, tuple[float, float]]]:
    """(scene, render seed, spp) -> {method: (relMSE, PSNR)} over the reports' rows; the first report
    to hold an image, spp and method wins."""
    d: dict[tuple[str, int | None, int], dict[str, tuple[float, float]]] = collections.defaultdict(dict)
    for f in files:
        doc = json.load(open(f))
        seeds = {im["id"]: im.get("seed") for im in doc.get("images", []) if "seed" in im}
        for x in doc["rows"]:
            # The scene is the image folder's name up to its first "_"; the folder above it (e.g.
            # `--data data/scene_inputs`) may hold "_" too, so it must not enter the key.
            key = (x["image"].rsplit("/", 1)[-1].split("_")[0], _seed(x["image"], seeds), x["spp"])
            d[key].setdefault(x["method"], (x["relmse"], x["psnr"]))
    return d


def scene_ratios(sc: dict[tuple[str, int | None], dict[str, tuple[float, float]]], old: str, new: str) -> dict[str, float]:
    """Per scene, NEW's mean relMSE over its renderings (seeds) divided by OLD's."""
    return {s: float(np.mean([v[new][0] for k, v in sc.items() if k[0] == s]) /
                     np.mean([v[old][0] for k, v in sc.items() if k[0] == s])) for s in sorted({k[0] for k in sc})}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("args", nargs="+", metavar="RESULTS_JSON... OLD NEW")
    ap.add_argument("--baseline", default="oidn-high")
    ap.add_argument("--per-scene", action="store_true",
                    help="also print, per scene, NEW's mean relMSE over the seeds divided by OLD's")
    ap.add_argument("--exclude", nargs="+", default=[], metavar="SCENE",
                    help="leave these scenes out of every figure (how much one scene decides a mean)")
    a = ap.parse_args()
    if len(a.args) < 3:
        ap.error("give one or more results.json, then OLD and NEW")
    *files, old, new = a.args
    d = collect(files)
    unknown = set(a.exclude) - {k[0] for k in d}
    if unknown:
        ap.error(f"--exclude: no scene {', '.join(sorted(unknown))} in the reports")
    d = {k: v for k, v in d.items() if k[0] not in a.exclude}
    if a.exclude:
        print(f"without {', '.join(a.exclude)}:")
    for spp in sorted({k[2] for k in d}):
        sc = {k[:2]: v for k, v in d.items() if k[2] == spp and old in v and new in v}
        for m in (old, new, a.baseline, "noisy"):
            if all(m in v for v in sc.values()):
                print(f"{spp:>3} spp {m:<28} relMSE {np.mean([v[m][0] for v in sc.values()]):.5f}  "
                      f"PSNR {np.mean([v[m][1] for v in sc.values()]):.4f}")
        better = sum(v[new][0] < v[old][0] for v in sc.values())
        print(f"        {new} better than {old} on {better}/{len(sc)} scene renderings")
        for m in (old, new):
            bad = [f"{k[0]}" + (f" (seed {k[1]})" if k[1] is not None else "") for k, v in sorted(sc.items(), key=str)
                   if "noisy" in v and (v[m][0] > v["noisy"][0] or v[m][1] < v["noisy"][1])]
            print(f"        {m} worse than noisy on: {', '.join(bad) or 'none'}")
        seeds = sorted({k[1] for k in sc}, key=lambda x: (x is None, x or 0))
        if len(seeds) > 1:
            per = {s: {m: np.mean([v[m] for k, v in sc.items() if k[1] == s], axis=0) for m in (old, new)} for s in seeds}
            for s in seeds:
                print(f"        seed {s}: {old} {per[s][old][0]:.5f} / {per[s][old][1]:.4f}  "
                      f"{new} {per[s][new][0]:.5f} / {per[s][new][1]:.4f}")
            print(f"        {new}'s mean better on {sum(per[s][new][0] < per[s][old][0] for s in seeds)}/{len(seeds)} "
                  f"seeds in relMSE, {sum(per[s][new][1] > per[s][old][1] for s in seeds)}/{len(seeds)} in PSNR")
        else:
            print("        x " + a.baseline + ": " + " ".join(
                f"{k[0]} {v[new][0] / v[a.baseline][0]:.2f} ({v[old][0] / v[a.baseline][0]:.2f})"
                for k, v in sorted(sc.items(), key=str) if a.baseline in v))
        if a.per_scene:
            print(f"        {new} / {old}, mean relMSE per scene: " +
                  " ".join(f"{s} {r:.3f}" for s, r in scene_ratios(sc, old, new).items()))


if __name__ == "__main__":
    main()
