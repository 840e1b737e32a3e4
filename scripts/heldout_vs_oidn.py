"""Models against OIDN 2.5.1 high on our own held-out images: rich_val and the val splits of
rich_ref 1-3 and of both Cycles sets (45 images per spp), never the third-party scenes.

    .venv/bin/python scripts/heldout_vs_oidn.py MODEL [MODEL ...] [--roots DATASET ...]

With ``--emitter-oidn R ...`` each model also gets a row per R with plain OIDN high written at
every emitter pixel (an albedo above 1, Cycles' convention) and within R pixels of one: the rule
tried for the combiner in docs/models/combine.md ("Tried, not kept").

Per spp (4, 8, 16; a pixel-only Cycles image counts at its own spp) and model: the mean,
geometric mean, median and worst ratio of relMSE to OIDN high's on the same image, how many
images it beats OIDN on and is within 5% of it, and the mean PSNR gain.
"""
import argparse
import warnings
from pathlib import Path

import numpy as np

import mcdenoise
from mcdenoise.data.dataset import Dataset
from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.eval.oidn import oidn_denoise

warnings.simplefilter("ignore")  # Blender-convention notes on every Cycles image
ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("models", nargs="+")
ap.add_argument("--roots", nargs="+", type=Path, help="datasets (their val split) or image folders; default: the six above",
                default=[Path(p) for p in ("data/rich_val", "data/rich_ref", "data/rich_ref2", "data/rich_ref3",
                                           "data/cycles_ref", "data/cycles_ref2")])
ap.add_argument("--emitter-oidn", nargs="+", type=int, default=[], metavar="R",
                help="also score each model with plain OIDN at and within R px of emitter pixels")
args = ap.parse_args()
models = args.models
rows = models + [f"{m}+emitter_oidn{r}" for m in models for r in args.emitter_oidn]


def _near_emitter(albedo: np.ndarray, r: int) -> np.ndarray:
    """(H, W) bool: pixels within ``r`` (Chebyshev) of one whose albedo exceeds 1 in any channel."""
    import torch
    import torch.nn.functional as F

    m = torch.from_numpy(np.ascontiguousarray(albedo.max(axis=0) > 1))[None, None].float()
    return (F.max_pool2d(m, 2 * r + 1, stride=1, padding=r)[0, 0] > 0).numpy()
folders = []
for root in args.roots:
    if (root / "manifest.json").is_file():
        folders += [im.path for im in Dataset(root).images("val") if im.has_reference]
    else:
        folders += sorted(m.parent for m in root.rglob("meta.json") if (m.parent / "reference.exr").is_file())
for spp in (4, 8, 16):
    R = {m: [] for m in rows}; D = {m: [] for m in rows}
    for f in folders:
        im = ImageFolder(f)
        # Depth and the diffuse/specular split where the image has them (a kernel-model
        # candidate, combine ens_kpcn, reads them), as scripts/blend_probe.py passes them.
        names = ["radiance", "albedo", "normal"] + [c for c in ("depth", "diffuse", "specular") if c in im.meta.channels]
        if im.samples is None:
            if im.meta.spp != spp: continue
            px = im.read_noisy(names)
        else:
            smp = im.samples.read(names, samples=list(range(spp)))
            px = {k: v.mean(axis=0) for k, v in smp.items()}
        ref = im.read_reference(["radiance"])["radiance"]
        o = oidn_denoise(px["radiance"], px["albedo"], px["normal"], threads=2)
        r0, p0 = relmse(o, ref), psnr(o, ref)
        for m in models:
            out = np.asarray(mcdenoise.denoise(px["radiance"], px["albedo"], px["normal"], depth=px.get("depth"),
                                               features={c: px[c] for c in ("diffuse", "specular") if c in px}, model=m))
            R[m].append(relmse(out, ref) / r0); D[m].append(psnr(out, ref) - p0)
            for rad in args.emitter_oidn:
                ruled = np.where(_near_emitter(px["albedo"], rad)[None], o, out)
                R[f"{m}+emitter_oidn{rad}"].append(relmse(ruled, ref) / r0)
                D[f"{m}+emitter_oidn{rad}"].append(psnr(ruled, ref) - p0)
    for m in rows:
        r = np.array(R[m])
        print(f"spp {spp:2d} {m[-32:]:<32} n={len(r)} mean {r.mean():.3f} geo {np.exp(np.log(r).mean()):.3f} median {np.median(r):.3f} worst {r.max():.3f} better {(r<1).sum()}/{len(r)} within5% {(r<=1.05).sum()} dPSNR {np.mean(D[m]):+.2f}", flush=True)
