"""Fixed per-pixel blends of saved denoiser outputs, scored like ``mcdenoise eval`` scores methods.

Reads a report written with ``mcdenoise eval ... --save-images`` (``OUT/images/IMAGE/Kspp/METHOD.exr``
and ``OUT/images/IMAGE/reference.exr``), forms each blend from its members' outputs and prints, per
spp, the mean relMSE (arithmetic, and geometric: less ruled by one outlier) and PSNR of every
member and blend, the ratio to a baseline, the per-image
oracle (the best member of each image: what a perfect per-image chooser could reach), and, when
the images carry render seeds, each seed's mean relMSE ratio to the baseline.

    python scripts/blend_outputs.py reports/c24_heldout --blend lm+kp=layer-medium+kpcn-pixel \\
        --blend med3=median:layer-medium+kpcn-pixel+sbmc [--baseline oidn-high]

A blend is ``NAME=A+B[+C...]`` (the per-pixel mean), ``NAME=median:A+B+C`` (the per-pixel median)
or ``NAME=0.6*A+0.4*B`` (fixed weights, which must sum to 1). No blend is fitted here: the weights
are what the command line says, so nothing is tuned to the images scored.
"""
from __future__ import annotations

import argparse
import collections
import json
import re
import sys
from pathlib import Path

import numpy as np

from mcdenoise.eval.scores import image_metrics
from mcdenoise.io.exr import read_exr

Blend = tuple[str, str, list[tuple[float, str]]]  # name, "mean" | "median", (weight, member)


def parse_blend(spec: str) -> Blend:
    """``NAME=A+B``, ``NAME=median:A+B+C`` or ``NAME=0.6*A+0.4*B`` -> (name, kind, [(weight, member)])."""
    if "=" not in spec:
        raise ValueError(f"--blend {spec!r}: expected NAME=A+B")
    name, rhs = spec.split("=", 1)
    kind = "mean"
    if rhs.startswith("median:"):
        kind, rhs = "median", rhs[len("median:"):]
    parts = [p for p in rhs.split("+") if p]
    if len(parts) < 2:
        raise ValueError(f"--blend {spec!r}: a blend needs two members or more")
    members: list[tuple[float, str]] = []
    for p in parts:
        m = re.fullmatch(r"([0-9.]+)\*(.+)", p)
        members.append((float(m.group(1)), m.group(2)) if m else (1.0 / len(parts), p))
    if kind == "median" and any(m for m in parts if "*" in m):
        raise ValueError(f"--blend {spec!r}: a median takes no weights")
    total = sum(w for w, _ in members)
    if abs(total - 1.0) > 1e-6:
        raise ValueError(f"--blend {spec!r}: the weights sum to {total:g}, not 1")
    return name, kind, members


def apply_blend(blend: Blend, outputs: dict[str, np.ndarray]) -> np.ndarray:
    """(3, H, W) blend of the members' (3, H, W) outputs."""
    _, kind, members = blend
    if kind == "median":
        return np.median(np.stack([outputs[m] for _, m in members]), axis=0)
    return sum(np.float32(w) * outputs[m] for w, m in members)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="report folder of `mcdenoise eval --save-images`")
    ap.add_argument("--blend", action="append", default=[], help="NAME=A+B, NAME=median:A+B+C or NAME=0.6*A+0.4*B")
    ap.add_argument("--baseline", default="oidn-high")
    ap.add_argument("--per-image", action="store_true", help="also print every image's relMSE")
    a = ap.parse_args()
    try:
        blends = [parse_blend(s) for s in a.blend]
    except ValueError as e:
        sys.exit(f"blend_outputs: {e}")
    root = a.report / "images"
    if not root.is_dir():
        sys.exit(f"blend_outputs: {root}: no saved images (run mcdenoise eval with --save-images)")
    doc = json.loads((a.report / "results.json").read_text())
    seeds = {im["id"]: im.get("seed") for im in doc.get("images", [])}
    methods = [m["name"] for m in doc["methods"]]
    members = sorted({m for b in blends for _, m in b[2]})
    missing = [m for m in members + [a.baseline] if m not in methods]
    if missing:
        sys.exit(f"blend_outputs: {a.report}: no method(s) {missing}; it has {methods}")
    names = [m for m in methods if m != "noisy"] + [b[0] for b in blends] + ["oracle(members)"]
    # scores[spp][name] -> list of (image, relmse, psnr)
    scores: dict[int, dict[str, list[tuple[str, float, float]]]] = collections.defaultdict(lambda: collections.defaultdict(list))
    image_ids = sorted({r["image"] for r in doc["rows"]})
    for iid in image_ids:
        folder = root / iid
        ref = read_exr(folder / "reference.exr")["radiance"]
        for kdir in sorted(folder.glob("*spp"), key=lambda p: int(p.name[:-3])):
            k = int(kdir.name[:-3])
            outs = {m: read_exr(kdir / f"{m}.exr")["radiance"] for m in methods if (kdir / f"{m}.exr").is_file()}
            for b in blends:
                outs[b[0]] = apply_blend(b, outs)
            for name, y in outs.items():
                if name not in names:
                    continue
                s = image_metrics(y, ref, ["relmse", "psnr"])
                scores[k][name].append((iid, float(s["relmse"]), float(s["psnr"])))
            if members:
                best = min((scores[k][n][-1] for n in members), key=lambda t: t[1])
                scores[k]["oracle(members)"].append(best)
    for k in sorted(scores):
        base = np.mean([r for _, r, _ in scores[k][a.baseline]])
        print(f"\n{k} spp, {len(scores[k][a.baseline])} images; ratio = mean relMSE / {a.baseline}'s")
        print(f"{'method':<28} {'relMSE':>8} {'ratio':>6} {'geo':>8} {'PSNR':>8}   per-seed ratio")
        by_seed_base = collections.defaultdict(list)
        for iid, r, _ in scores[k][a.baseline]:
            by_seed_base[seeds.get(iid)].append(r)
        for name in names:
            rows = scores[k].get(name, [])
            if not rows:
                continue
            rel = np.mean([r for _, r, _ in rows])
            geo = float(np.exp(np.mean(np.log([max(r, 1e-12) for _, r, _ in rows]))))  # outliers weigh less
            ps = np.mean([p for _, _, p in rows])
            by_seed = collections.defaultdict(list)
            for iid, r, _ in rows:
                by_seed[seeds.get(iid)].append(r)
            per_seed = ""
            if 1 < len(by_seed) < len(rows):  # seeds shared by several images (a scene set rendered per seed)
                per_seed = " ".join(f"{np.mean(by_seed[s]) / np.mean(by_seed_base[s]):.2f}"
                                    for s in sorted(by_seed, key=lambda s: (s is None, s)))
            print(f"{name:<28} {rel:8.4f} {rel / base:6.2f} {geo:8.4f} {ps:8.3f}   {per_seed}")
        if a.per_image:
            cols = [n for n in names if scores[k].get(n)]
            print("image " + " ".join(f"{n[:12]:>12}" for n in cols))
            for i, iid in enumerate(image_ids):
                print(f"{iid} " + " ".join(f"{scores[k][n][i][1]:12.4f}" for n in cols))


if __name__ == "__main__":
    main()
