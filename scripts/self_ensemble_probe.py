"""How a model's 8 orientations combine (campaign 20, docs/TRAINING.md): on held-out images, each
model's geometric-mean and mean relMSE and mean PSNR for one pass and for the per-pixel mean,
median and trimmed means of its 8 orientations (:mod:`mcdenoise.models.symmetry`). Each pass runs
as ``eval`` runs it (the model's own consistency clamp inside). With ``--per-op``, also each
orientation alone, and the image whose worst orientation is worst.

    python scripts/self_ensemble_probe.py data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val --models layer-medium --spp 4 8 16
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from mcdenoise.eval.images import collect_images
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.models.symmetry import ALL_OPS, median_of, transform_batch, untransform
from mcdenoise.models.weights import load_denoiser


def aggregates(passes: np.ndarray) -> dict[str, np.ndarray]:
    """``passes (8, 3, H, W)`` -> each way of combining them."""
    srt = np.sort(passes, 0)
    return {"one pass": passes[0], "mean": passes.mean(0), "median": median_of(list(passes)),
            "trim 1": srt[1:-1].mean(0), "trim 2": srt[2:-2].mean(0)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--models", nargs="+", required=True)
    ap.add_argument("--spp", nargs="+", type=int, default=[4, 8, 16])
    ap.add_argument("--per-op", action="store_true")
    a = ap.parse_args()
    images = [e.folder for e in collect_images(a.roots, split="val")[0]]
    for spec in a.models:
        m, info = load_denoiser(spec)
        meth = ModelMethod(spec, m, info, "cpu")
        for spp in a.spp:
            res: dict[str, list] = {}
            per_op = []
            for im in images:
                ref = im.read_reference(["radiance"])["radiance"]
                batch = meth.prepare(Inputs(im, spp))
                with torch.inference_mode():
                    passes = np.stack([untransform(meth.run(transform_batch(batch, op)), op) for op in ALL_OPS])
                per_op.append([relmse(p, ref) for p in passes])
                for key, out in aggregates(passes).items():
                    res.setdefault(key, []).append((relmse(out, ref), psnr(out, ref)))
            for key, v in res.items():
                v = np.array(v)
                print(f"{spec} spp {spp:2d} {key:9s}: relMSE geo {np.exp(np.log(v[:, 0]).mean()):.5f} mean {v[:, 0].mean():.5f}"
                      f"  PSNR {v[:, 1].mean():.4f}  ({len(v)} images)", flush=True)
            if a.per_op:
                r = np.array(per_op)
                print(f"{spec} spp {spp:2d} per orientation, geo relMSE: " + " ".join(f"{x:.5f}" for x in np.exp(np.log(r).mean(0))))
                w = int(np.argmax(r.max(1)))
                print(f"{spec} spp {spp:2d} worst image {images[w].path}: relMSE per orientation " + " ".join(f"{x:.3g}" for x in r[w]))


if __name__ == "__main__":
    main()
