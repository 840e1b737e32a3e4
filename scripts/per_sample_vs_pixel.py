"""Where per-sample information pays (issue 19): per scene and spp, the relMSE of each sample model
relative to the pixel model trained on the same data and to OIDN 2.5.1 high, from an eval report.

    python scripts/per_sample_vs_pixel.py reports/valscenes/results.csv --sample layer sbmc --pixel kpcn-pixel

The papers' claim (SBMC, layer embeddings) is that per-sample input wins at low sample counts. A
ratio below 1 in the "/ pixel" column is a scene where it does here. A ratio below 1 in the
"/ OIDN" column is a scene where the sample model beats OIDN high. The last rows count both
per spp.
"""
from __future__ import annotations

import argparse
import csv
from collections import defaultdict

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("csv")
    ap.add_argument("--sample", nargs="+", default=["layer", "sbmc"])
    ap.add_argument("--pixel", default="kpcn-pixel")
    ap.add_argument("--oidn", default="oidn-high")
    a = ap.parse_args()
    r: dict[tuple[str, int, str], float] = {}
    for row in csv.DictReader(open(a.csv)):
        r[(row["image"].split("_")[0], int(row["spp"]), row["method"])] = float(row["relmse"])
    scenes = sorted({k[0] for k in r})
    spps = sorted({k[1] for k in r})
    cols = [f"{m} / {ref}" for m in a.sample for ref in (a.pixel, "OIDN")]
    print("| scene | spp | " + " | ".join(cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    wins: dict[tuple[str, str, int], int] = defaultdict(int)
    means: dict[tuple[str, int], list[float]] = defaultdict(list)
    for sc in scenes:
        for spp in spps:
            cells = []
            for m in a.sample:
                for ref_name, ref in ((a.pixel, a.pixel), ("OIDN", a.oidn)):
                    q = r[(sc, spp, m)] / r[(sc, spp, ref)]
                    wins[(m, ref_name, spp)] += q < 1
                    cells.append(f"{q:.2f}")
            print(f"| {sc} | {spp} | " + " | ".join(cells) + " |")
    print()
    for spp in spps:
        for m in [*a.sample, a.pixel, a.oidn]:
            means[(m, spp)] = [r[(sc, spp, m)] for sc in scenes]
        parts = [f"{m}: better than {a.pixel} on {wins[(m, a.pixel, spp)]}, than OIDN high on {wins[(m, 'OIDN', spp)]} "
                 f"of {len(scenes)} (mean relMSE {np.mean(means[(m, spp)]):.4f})" for m in a.sample]
        print(f"- {spp} spp: " + "; ".join(parts) + f"; {a.pixel} {np.mean(means[(a.pixel, spp)]):.4f}, "
              f"OIDN high {np.mean(means[(a.oidn, spp)]):.4f}")


if __name__ == "__main__":
    main()
