"""Where per-sample information pays (issue 19): per scene and spp, the relMSE of each sample model
relative to the pixel model trained on the same data and to OIDN 2.5.1 high, from an eval report.

    python scripts/per_sample_vs_pixel.py reports/valscenes/results.csv --sample layer sbmc --pixel kpcn-pixel
    python scripts/per_sample_vs_pixel.py reports/valscenes_seeds/results.csv --sample layer-medium

The papers' claim (SBMC, layer embeddings) is that per-sample input wins at low sample counts. A
ratio below 1 in the "/ pixel" column is a scene where it does here. A ratio below 1 in the
"/ OIDN" column is a scene where the sample model beats OIDN high. The last rows count both
per spp, over scenes and over renderings.

A report may hold several renderings of a scene (render seeds, ``<scene>_..._seed<N>`` under any
folder): a scene's ratio is the ratio of its mean relMSE over them, and the means are over every
rendering, so they match the report's own means.
"""
from __future__ import annotations

import argparse
import csv
from collections import defaultdict

import numpy as np


def scene_of(image: str) -> str:
    """The scene of a report image, under any folder (``data/scene_inputs/bathroom_128x128_...``)."""
    return image.rsplit("/", 1)[-1].split("_")[0]


def read(path: str) -> dict[tuple[str, int, str], dict[str, float]]:
    """(scene, spp, method) -> {image: relMSE}; the first row of an (image, spp, method) wins."""
    r: dict[tuple[str, int, str], dict[str, float]] = defaultdict(dict)
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            r[(scene_of(row["image"]), int(row["spp"]), row["method"])].setdefault(row["image"], float(row["relmse"]))
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("csv")
    ap.add_argument("--sample", nargs="+", default=["layer", "sbmc"])
    ap.add_argument("--pixel", default="kpcn-pixel")
    ap.add_argument("--oidn", default="oidn-high")
    a = ap.parse_args()
    r = read(a.csv)
    scenes = sorted({k[0] for k in r})
    spps = sorted({k[1] for k in r})
    cols = [f"{m} / {ref}" for m in a.sample for ref in (a.pixel, "OIDN")]
    print("| scene | spp | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    wins: dict[tuple[str, str, int], int] = defaultdict(int)
    render_wins: dict[tuple[str, str, int], int] = defaultdict(int)
    n_render: dict[int, int] = defaultdict(int)
    for sc in scenes:
        for spp in spps:
            cells = []
            for m in a.sample:
                for ref_name, ref in ((a.pixel, a.pixel), ("OIDN", a.oidn)):
                    mine, theirs = r[(sc, spp, m)], r[(sc, spp, ref)]
                    common = sorted(set(mine) & set(theirs))
                    q = float(np.mean([mine[i] for i in common]) / np.mean([theirs[i] for i in common]))
                    wins[(m, ref_name, spp)] += q < 1
                    render_wins[(m, ref_name, spp)] += sum(mine[i] < theirs[i] for i in common)
                    cells.append(f"{q:.2f}")
            n_render[spp] += len(r[(sc, spp, a.oidn)])
            print(f"| {sc} | {spp} | " + " | ".join(cells) + " |")
    print()
    for spp in spps:
        def mean(m: str) -> float:
            return float(np.mean([v for sc in scenes for v in r[(sc, spp, m)].values()]))
        parts = [f"{m}: better than {a.pixel} on {wins[(m, a.pixel, spp)]}, than OIDN high on {wins[(m, 'OIDN', spp)]} "
                 f"of {len(scenes)} scenes ({render_wins[(m, a.pixel, spp)]} and {render_wins[(m, 'OIDN', spp)]} of "
                 f"{n_render[spp]} renderings; mean relMSE {mean(m):.4f})" for m in a.sample]
        print(f"- {spp} spp: " + "; ".join(parts) + f"; {a.pixel} {mean(a.pixel):.4f}, OIDN high {mean(a.oidn):.4f}")


if __name__ == "__main__":
    main()
