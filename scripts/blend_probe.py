"""Probe (issue 20, worst scene): how far a fixed blend ``OIDN + a * (model - OIDN)`` moves the
mean and the worst per-scene relMSE ratio to OIDN 2.5.1 high. relMSE and PSNR against the
references stored in each image folder; inputs are the first ``spp`` samples (a pixel-only image,
such as a converted Cycles render, counts at its own spp only).

    python scripts/blend_probe.py data/rich_val data/rich_ref data/rich_ref2 data/rich_ref3 --model mcdenoise/models/shipped/combine-ens.safetensors --spp 4 8 16
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import mcdenoise
from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.data.stats import pixel_stats
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.eval.oidn import oidn_denoise


#: Channels passed beside colour, albedo and normal when an image has them.
EXTRA = ("depth", "diffuse", "specular")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("roots", nargs="+", help="image folders under these; a dataset (manifest.json) gives its val split")
    ap.add_argument("--model", required=True)
    ap.add_argument("--spp", nargs="+", type=int, default=[8])
    ap.add_argument("--alphas", nargs="+", type=float, default=[1.0, 0.9, 0.8, 0.7, 0.5])
    a = ap.parse_args()
    folders = []
    for root in map(Path, a.roots):
        if (root / "manifest.json").is_file():
            from mcdenoise.data.dataset import Dataset

            folders += [im.path for im in Dataset(root).images("val") if im.has_reference]
        else:
            folders += sorted(m.parent for m in root.rglob("meta.json") if (m.parent / "reference.exr").is_file())
    for spp in a.spp:
        ratios = {al: [] for al in a.alphas}
        dps = {al: [] for al in a.alphas}
        for f in folders:
            im = ImageFolder(f)
            ref = im.read_reference(["radiance"])["radiance"]
            # What a kernel-model candidate (combine ens_kpcn) also reads, where the image has it.
            names = ["radiance", "albedo", "normal"] + [c for c in EXTRA if c in im.meta.channels]
            if im.samples is None:  # a pixel-only image (e.g. a converted Cycles render): its own spp only
                if im.meta.spp != spp:
                    continue
                px = im.read_noisy(names)
            else:
                smp = im.samples.read(names, samples=list(range(spp)))
                px = {k: v.mean(axis=0) for k, v in smp.items()}
            oidn = oidn_denoise(px["radiance"], px["albedo"], px["normal"], threads=2)
            out = np.asarray(mcdenoise.denoise(px["radiance"], px["albedo"], px["normal"], depth=px.get("depth"),
                                               features={c: px[c] for c in ("diffuse", "specular") if c in px},
                                               model=a.model))
            r0, p0 = relmse(oidn, ref), psnr(oidn, ref)
            for al in a.alphas:
                mix = oidn + al * (out - oidn)
                ratios[al].append(relmse(mix, ref) / r0)
                dps[al].append(psnr(mix, ref) - p0)
        for al in a.alphas:
            r = np.array(ratios[al])
            print(f"spp {spp:2d} alpha {al:.2f}: mean ratio {r.mean():.3f} (geo {np.exp(np.log(r).mean()):.3f}), "
                  f"worst {r.max():.3f}, better on {(r < 1).sum()}/{len(r)}, dPSNR {np.mean(dps[al]):+.2f} dB")


if __name__ == "__main__":
    main()
