"""Probe (issue 20): OIDN 2.5.1 high beside the shipped kpcn-pixel and wskp on held-out images, their
means, and the per-pixel oracles over {OIDN, kpcn-pixel} and {OIDN, kpcn-pixel, noisy mean}: how
much a combiner with a kernel-model candidate could gain (docs/models/combine.md, campaign 10).
Per spp (4, 8, 16): each candidate's relMSE relative to OIDN high on the same image (mean,
geometric mean, worst), how many images it beats OIDN on, and the mean PSNR gain.

    python scripts/kernel_oracle_probe.py data/rich_val data/rich_ref data/rich_ref2 data/rich_ref3 data/cycles_ref data/cycles_ref2

A dataset (manifest.json) gives its val split; a pixel-only image counts at its own spp only.
"""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

import mcdenoise
from mcdenoise.data.dataset import Dataset
from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.eval.oidn import oidn_denoise

CHANNELS = ["radiance", "albedo", "normal", "diffuse", "specular", "depth"]


def oracle(cands: list[np.ndarray], ref: np.ndarray) -> np.ndarray:
    """``(3, H, W)``: per pixel, the candidate closest to ``ref`` (L1 over colour)."""
    st = np.stack(cands)
    pick = np.abs(st - ref).sum(1, keepdims=True).argmin(0)[None].repeat(3, 1)
    return np.take_along_axis(st, pick, 0)[0]


def folders(roots: list[Path]) -> list[Path]:
    out = []
    for root in roots:
        if (root / "manifest.json").is_file():
            out += [im.path for im in Dataset(root).images("val") if im.has_reference]
        else:
            out += sorted(m.parent for m in root.rglob("meta.json") if (m.parent / "reference.exr").is_file())
    return out


def main() -> None:
    warnings.simplefilter("ignore")  # Blender-convention notes on every Cycles image
    images = folders([Path(p) for p in sys.argv[1:]])
    for spp in (4, 8, 16):
        rows: dict[str, list[tuple[float, float]]] = {}
        for f in images:
            im = ImageFolder(f)
            if im.samples is None:
                if im.meta.spp != spp:
                    continue
                px = im.read_noisy(CHANNELS)
            else:
                px = {k: v.mean(axis=0) for k, v in im.samples.read(CHANNELS, samples=list(range(spp))).items()}
            ref = im.read_reference(["radiance"])["radiance"]
            c, al, nr, dp = px["radiance"], px["albedo"], px["normal"], px["depth"]
            o = oidn_denoise(c, al, nr, threads=1)
            k = np.asarray(mcdenoise.denoise(c, al, nr, depth=dp, features={"diffuse": px["diffuse"], "specular": px["specular"]},
                                             model="kpcn-pixel"))
            w = np.asarray(mcdenoise.denoise(c, al, nr, depth=dp, model="wskp"))
            cands = {"oidn": o, "kpcn": k, "wskp": w, "mean_ok": 0.5 * (o + k), "mean_ow": 0.5 * (o + w),
                     "mean3": (o + k + w) / 3, "oracle_okn": oracle([o, k, c], ref), "oracle_ok": oracle([o, k], ref)}
            r0, p0 = relmse(o, ref), psnr(o, ref)
            for n, x in cands.items():
                rows.setdefault(n, []).append((relmse(x, ref) / r0, psnr(x, ref) - p0))
        for n, v in rows.items():
            a = np.array(v)
            print(f"spp {spp:2d} {n:12s} n={len(a)} mean {a[:, 0].mean():.3f} geo {np.exp(np.log(a[:, 0]).mean()):.3f} "
                  f"worst {a[:, 0].max():.3f} better {(a[:, 0] < 1).sum()} dPSNR {a[:, 1].mean():+.2f}", flush=True)


if __name__ == "__main__":
    main()
