"""Do a model's gains or losses against another follow small bright lights? Per image of an eval
report: the share of the reference's light in its N brightest pixels (a small bright emitter gives a
large share), and the ratio of NEW's relMSE to OLD's; then, per NEW, the Spearman rank correlation
of the two over the images. Campaign 25 asked it of our held-out images, to see whether any of them
behave like a third-party scene whose 4-spp relMSE is held by pixels beside a small bright window.

    python scripts/bright_share_vs_ratio.py reports/c25_heldout4/results.json layer-medium m25c_a25_k3at8 m25ft_a25_k3at8 --spp 4
"""
from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

import numpy as np

from mcdenoise.io.exr import read_exr


def bright_share(radiance: np.ndarray, n: int) -> float:
    """radiance (H, W, 3) -> the fraction of the summed luminance held by the n brightest pixels."""
    lum = np.sort(np.asarray(radiance, dtype=np.float64).mean(axis=-1).ravel())
    total = lum.sum()
    return float(lum[-n:].sum() / total) if total > 0 else 0.0


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation (ties broken by order; the shares and ratios here are continuous)."""
    ra, rb = np.argsort(np.argsort(a)), np.argsort(np.argsort(b))
    return float(np.corrcoef(ra, rb)[0, 1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="results.json of `mcdenoise eval`")
    ap.add_argument("old", help="the method every ratio is taken against")
    ap.add_argument("new", nargs="+", help="methods whose relMSE is divided by OLD's")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--pixels", type=int, default=16, help="how many brightest pixels make the share")
    a = ap.parse_args()
    doc = json.loads(a.report.read_text())
    paths = {im["id"]: im["path"] for im in doc["images"]}
    rel: dict[str, dict[str, float]] = collections.defaultdict(dict)
    for r in doc["rows"]:
        if r["spp"] == a.spp:
            rel[r["image"]][r["method"]] = r["relmse"]
    missing = [m for m in (a.old, *a.new) if not any(m in v for v in rel.values())]
    if missing:
        ap.error(f"{a.report}: no rows at {a.spp} spp for {', '.join(missing)}")
    ids = sorted(i for i, v in rel.items() if all(m in v for m in (a.old, *a.new)))
    share = np.array([bright_share(read_exr(Path(paths[i]) / "reference.exr")["radiance"], a.pixels) for i in ids])
    ratio = {m: np.array([rel[i][m] / rel[i][a.old] for i in ids]) for m in a.new}
    print(f"{'image':<36} share  " + "  ".join(f"{m[:16]:>16}" for m in a.new))
    for k in np.argsort(-share):
        print(f"{ids[k]:<36} {share[k]:.3f}  " + "  ".join(f"{ratio[m][k]:>16.3f}" for m in a.new))
    top = share >= np.quantile(share, 0.75)
    for m in a.new:
        print(f"{m}: worse than {a.old} on {int((ratio[m] > 1).sum())} of {len(ids)}; geometric-mean ratio "
              f"{np.exp(np.log(ratio[m]).mean()):.4f} (brightest-share quarter {np.exp(np.log(ratio[m][top]).mean()):.4f}); "
              f"Spearman with the share {spearman(share, ratio[m]):+.3f}")


if __name__ == "__main__":
    main()
