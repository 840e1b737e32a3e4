"""How far a new eval report moves from a generated block of docs/RESULTS.md: the same command run
on another CPU, or after a change that should not alter the figures.

    python scripts/results_block_drift.py reports/X/results.json --section valscenes

Per method and spp: the mean relMSE and PSNR of the block and of the report, and over the images
of the block's "relMSE per image" tables the median and largest |new / old - 1|; per image, the
largest for the noisy input and for any other method. The block prints 4 significant digits, so
differences under ~5e-4 relative are its rounding. Then, from the report
alone, every (method, spp, image) where a model is worse than the noisy input in relMSE or PSNR
(issue 19's first done-when item).

Means are over every image of the report. A per-image table row is paired with a report image only
when its label (a scene name; ``proc`` in the procedural-test block) names exactly one row of its
table and exactly one image of the report: a six-seed report (54 renderings of 9 scenes) against
the seed-7 block, or the procedural block's repeated ``proc`` rows, give no pairs, and the script
says so instead of pairing the wrong images.
"""
from __future__ import annotations

import argparse
import collections
import json
import re
from pathlib import Path

import numpy as np

NOT_MODELS = ("noisy", "oidn-high", "oidn-fast", "oidn-high-pf")


def block_lines(results_md: Path, section: str) -> list[str]:
    text = results_md.read_text()
    m = re.search(rf"<!-- BEGIN generated:eval:{re.escape(section)} -->\n(.*?)<!-- END generated:eval:{re.escape(section)} -->",
                  text, re.S)
    if m is None:
        raise SystemExit(f"{results_md}: no generated block '{section}'")
    return m.group(1).splitlines()


def _table(lines: list[str], start: int) -> list[list[str]]:
    """The markdown table that begins at or after ``start``: header row, then data rows."""
    i = start
    while i < len(lines) and not lines[i].startswith("|"):
        i += 1
    rows = []
    while i < len(lines) and lines[i].startswith("|"):
        cells = [c.strip().strip("*") for c in lines[i].strip("|").split("|")]
        if not set(lines[i]) <= set("|-: "):
            rows.append(cells)
        i += 1
    return rows


def parse_block(lines: list[str]) -> tuple[dict[tuple[str, int], tuple[float, float]], dict[tuple[str, int, str], float]]:
    """(method, spp) -> (mean relMSE, mean PSNR) from the first means table, and
    (method, spp, image) -> relMSE from the "relMSE per image at N spp" tables."""
    means: dict[tuple[str, int], tuple[float, float]] = {}
    first = next(i for i, s in enumerate(lines) if s.startswith("| spp | method |"))
    head, *rows = _table(lines, first)
    for r in rows:
        means[(r[1], int(r[0]))] = (float(r[head.index("relMSE")]), float(r[head.index("PSNR")]))
    per: dict[tuple[str, int, str], float] = {}
    for i, s in enumerate(lines):
        m = re.match(r"relMSE per image at (\d+) spp", s)
        if m:
            head, *rows = _table(lines, i + 1)
            labels = collections.Counter(r[0] for r in rows)
            for r in rows:
                if labels[r[0]] > 1:  # e.g. the procedural block's "proc" rows: no image to pair with
                    continue
                for method, v in zip(head[1:], r[1:]):
                    per[(method, int(m.group(1)), r[0])] = float(v)
    return means, per


def image_key(image: str) -> str:
    """A report image's own name (unique per rendering: scene, size, depth, seed)."""
    return image.rsplit("/", 1)[-1]


def scene_of(image: str) -> str:
    return image_key(image).split("_")[0]


def pairs(images: list[str]) -> dict[str, str]:
    """Block label -> the one report image of that scene; scenes with several images are left out."""
    by: dict[str, list[str]] = collections.defaultdict(list)
    for im in images:
        by[scene_of(im)].append(im)
    return {label: ims[0] for label, ims in by.items() if len(ims) == 1}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="results.json of the new run")
    ap.add_argument("--section", default="valscenes")
    ap.add_argument("--results-md", type=Path, default=Path("docs/RESULTS.md"))
    a = ap.parse_args()
    means, per = parse_block(block_lines(a.results_md, a.section))
    doc = json.loads(a.report.read_text())
    new: dict[tuple[str, int, str], tuple[float, float]] = {}
    for x in doc["rows"]:
        new[(x["method"], x["spp"], image_key(x["image"]))] = (x["relmse"], x["psnr"])
    paired = pairs(sorted({im for (_, _, im) in new}))
    print(f"{'method':18s} spp | mean relMSE block -> new | PSNR block -> new | per image |new/old-1|: median, max (image)")
    for (method, spp), (rel0, psnr0) in sorted(means.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        mine = {im: v for (me, s, im), v in new.items() if me == method and s == spp}
        if not mine:
            continue
        rel1 = float(np.mean([v[0] for v in mine.values()]))
        psnr1 = float(np.mean([v[1] for v in mine.values()]))
        dev = {label: abs(mine[paired[label]][0] / old - 1) for (me, s, label), old in per.items()
               if me == method and s == spp and paired.get(label) in mine}
        per_image = "no image pairs"
        if dev:
            worst = max(dev, key=dev.get)
            per_image = f"{np.median(list(dev.values())):.2e}, {dev[worst]:.2e} ({worst})"
        print(f"{method:18s} {spp:3d} | {rel0:.4g} -> {rel1:.4g} ({rel1 / rel0 - 1:+.2%}) | {psnr0:.2f} -> {psnr1:.2f} "
              f"({psnr1 - psnr0:+.3f} dB) | {per_image}")
    # Per image, over every spp: the noisy input's largest drift (did the inputs come back?) and
    # the largest of any other method's.
    by_image: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0.0])
    for (method, spp, label), old in per.items():
        key = (method, spp, paired.get(label, ""))
        if key in new:
            d = abs(new[key][0] / old - 1)
            slot = by_image[label]
            slot[method != "noisy"] = max(slot[method != "noisy"], d)
    n_images = len({im for (_, _, im) in new})
    print(f"\nper image, largest |new/old-1| of relMSE: noisy input, any other method "
          f"({len(by_image)} of the report's {n_images} images paired with a block row)")
    for im, (dn, dm) in sorted(by_image.items()):
        print(f"  {im:16s} {dn:.2e}  {dm:.2e}")
    worse = collections.defaultdict(list)
    for (method, spp, im), (rel, psnr) in sorted(new.items()):
        if method in NOT_MODELS or ("noisy", spp, im) not in new:
            continue
        nrel, npsnr = new[("noisy", spp, im)]
        if rel >= nrel:
            worse[(method, spp)].append(f"{im} relMSE {rel:.4g} >= {nrel:.4g}")
        if psnr <= npsnr:
            worse[(method, spp)].append(f"{im} PSNR {psnr:.2f} <= {npsnr:.2f}")
    models = sorted({m for (m, _, _) in new} - set(NOT_MODELS))
    print(f"\nworse than the noisy input (relMSE or PSNR), from the report: "
          f"{sum(map(len, worse.values()))} of {sum(1 for k in new if k[0] in models)} (method, spp, image)")
    for k, v in sorted(worse.items()):
        print(f"  {k[0]} {k[1]} spp: " + "; ".join(v))


if __name__ == "__main__":
    main()
