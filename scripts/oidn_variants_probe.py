"""Probe: relMSE/PSNR of OIDN 2.5.1 variants and simple ensembles on image folders with references.

Variants: quality high/fast, with OIDN-prefiltered guides (albedo and normal denoised by OIDN
``fast`` alone, then cleanAux: ``oidn_denoise(..., prefilter="fast")``, the mode the ``ens``
combiner uses), and the mean of candidates. Prints one table per spp.

    python scripts/oidn_variants_probe.py data/rich_val data/scene_inputs --spp 4 8 16
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.data.stats import pixel_stats
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.eval.oidn import oidn_denoise, oidn_prefilter


def folders(roots):
    for r in roots:
        r = Path(r)
        for p in sorted(r.iterdir()):
            if (p / "meta.json").is_file() and (p / "reference.exr").is_file():
                yield p


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--spp", nargs="+", type=int, default=[4, 8, 16])
    a = ap.parse_args()
    rows: dict[tuple[str, int], dict[str, list[float]]] = {}
    for p in folders(a.roots):
        f = ImageFolder(p)
        ref = f.read_reference(["radiance"])["radiance"]
        group = p.parent.name
        for k in a.spp:
            smp = f.samples.read(["radiance", "albedo", "normal"], samples=list(range(k)))
            m = {n: pixel_stats(v)[0] for n, v in smp.items()}
            c, al, nr = m["radiance"], m["albedo"], m["normal"]
            # half buffers: even and odd samples
            hA = {n: pixel_stats(v[0::2])[0] for n, v in smp.items()}  # (S, C, H, W)
            hB = {n: pixel_stats(v[1::2])[0] for n, v in smp.items()}
            cand = {}
            cand["noisy"] = c
            cand["high"] = oidn_denoise(c, al, nr, quality="high")
            cand["fast"] = oidn_denoise(c, al, nr, quality="fast")
            alp, nrp = oidn_prefilter(al, "albedo"), oidn_prefilter(nr, "normal")
            cand["high_pf"] = oidn_denoise(c, alp, nrp, quality="high", clean_aux=True)
            cand["fast_pf"] = oidn_denoise(c, alp, nrp, quality="fast", clean_aux=True)
            cand["mean(high,fast)"] = 0.5 * (cand["high"] + cand["fast"])
            cand["mean(high,high_pf)"] = 0.5 * (cand["high"] + cand["high_pf"])
            cand["mean4"] = 0.25 * (cand["high"] + cand["fast"] + cand["high_pf"] + cand["fast_pf"])
            dA = oidn_denoise(hA["radiance"], alp, nrp, clean_aux=True)
            dB = oidn_denoise(hB["radiance"], alp, nrp, clean_aux=True)
            cand["mean(halves_pf)"] = 0.5 * (dA + dB)
            names = ["high", "fast", "high_pf", "fast_pf"]
            stack = np.stack([cand[n] for n in names])
            cand["oracle_px"] = np.take_along_axis(stack, np.abs(stack - ref).sum(1, keepdims=True).argmin(0)[None].repeat(3, 1), 0)[0]
            for n, x in cand.items():
                d = rows.setdefault((group, k), {})
                d.setdefault(n, []).append((float(relmse(x, ref)), float(psnr(x, ref))))
    print_table(rows)
    sys.stdout.flush()


def print_table(rows: dict[tuple[str, int], dict[str, list[tuple[float, float]]]]) -> None:
    """One table per (folder group, spp): each candidate's mean relMSE and PSNR, against ``high``."""
    for (group, k), d in sorted(rows.items()):
        print(f"\n{group} spp {k} ({len(d['high'])} images)")
        base = np.array(d["high"])
        for n, v in d.items():
            v = np.array(v)
            wins = int((v[:, 0] < base[:, 0]).sum())
            print(f"  {n:22s} relMSE {v[:,0].mean():.4f} ({v[:,0].mean()/base[:,0].mean():.3f}x high)  PSNR {v[:,1].mean():.2f}  beats high on {wins}/{len(v)}  worst ratio {np.max(v[:,0]/base[:,0]):.3f}")


if __name__ == "__main__":
    main()
