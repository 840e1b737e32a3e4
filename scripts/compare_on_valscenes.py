"""Two models side by side on an eval report of the third-party scenes: means, per-scene ratios to
OIDN high, how many scenes the new one improves, and where either is worse than the noisy input.

    python scripts/compare_on_valscenes.py reports/val_RUN/results.json OLD NEW [--baseline oidn-high]
"""
from __future__ import annotations

import argparse
import collections
import json

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results")
    ap.add_argument("old")
    ap.add_argument("new")
    ap.add_argument("--baseline", default="oidn-high")
    a = ap.parse_args()
    rows = json.load(open(a.results))["rows"]
    d: dict[tuple[str, int], dict[str, tuple[float, float]]] = collections.defaultdict(dict)
    for x in rows:
        d[(x["image"].split("_")[0], x["spp"])][x["method"]] = (x["relmse"], x["psnr"])
    for spp in sorted({k[1] for k in d}):
        sc = {k[0]: v for k, v in d.items() if k[1] == spp}
        for m in (a.old, a.new, a.baseline, "noisy"):
            if all(m in v for v in sc.values()):
                print(f"{spp:>3} spp {m:<28} relMSE {np.mean([v[m][0] for v in sc.values()]):.4f}  "
                      f"PSNR {np.mean([v[m][1] for v in sc.values()]):.2f}")
        better = sum(v[a.new][0] < v[a.old][0] for v in sc.values())
        print(f"        {a.new} better than {a.old} on {better}/{len(sc)}")
        for m in (a.old, a.new):
            bad = [k for k, v in sorted(sc.items()) if v[m][0] > v["noisy"][0] or v[m][1] < v["noisy"][1]]
            print(f"        {m} worse than noisy on: {', '.join(bad) or 'none'}")
        print("        x " + a.baseline + ": " + " ".join(
            f"{k} {v[a.new][0] / v[a.baseline][0]:.2f} ({v[a.old][0] / v[a.baseline][0]:.2f})" for k, v in sorted(sc.items())))


if __name__ == "__main__":
    main()
