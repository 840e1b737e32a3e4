"""Per-scene check of one method against OIDN high from an eval report's results.csv (issue 20's
criteria: mean relMSE and PSNR better, better on >= 2/3 of the images, never > 5% worse).

    python scripts/per_scene_vs_oidn.py reports/valscenes/results.csv METHOD [--baseline oidn-high]
"""
from __future__ import annotations

import argparse
import csv
from collections import defaultdict


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("csv")
    ap.add_argument("method")
    ap.add_argument("--baseline", default="oidn-high")
    a = ap.parse_args()
    rows: dict[tuple[str, int], dict[str, dict[str, float]]] = defaultdict(dict)
    with open(a.csv) as f:
        for r in csv.DictReader(f):
            rows[(r["image"], int(r["spp"]))][r["method"]] = {"relmse": float(r["relmse"]), "psnr": float(r["psnr"])}
    for spp in sorted({s for _, s in rows}):
        ims = sorted(i for i, s in rows if s == spp and a.method in rows[(i, s)] and a.baseline in rows[(i, s)])
        print(f"{spp} spp: {'image':34s} {a.method:>14s} {a.baseline:>12s}  ratio   dPSNR")
        ratios, dp = [], []
        for i in ims:
            m, b = rows[(i, spp)][a.method], rows[(i, spp)][a.baseline]
            ratios.append(m["relmse"] / b["relmse"])
            dp.append(m["psnr"] - b["psnr"])
            print(f"        {i[:34]:34s} {m['relmse']:14.4f} {b['relmse']:12.4f} {ratios[-1]:6.3f} {dp[-1]:+7.2f}")
        n = len(ims)
        mm = sum(rows[(i, spp)][a.method]["relmse"] for i in ims) / n
        mb = sum(rows[(i, spp)][a.baseline]["relmse"] for i in ims) / n
        wins = sum(r < 1 for r in ratios)
        worst = max(ratios)
        ok = mm < mb and sum(dp) > 0 and wins * 3 >= 2 * n and worst <= 1.05
        print(f"   mean relMSE {mm:.4f} vs {mb:.4f} ({mm / mb:.3f}x), mean dPSNR {sum(dp) / n:+.2f} dB, "
              f"better on {wins}/{n}, worst ratio {worst:.3f}: {'MET' if ok else 'not met'}")


if __name__ == "__main__":
    main()
