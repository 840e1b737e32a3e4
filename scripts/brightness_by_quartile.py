"""Does a model move light between dim and bright regions? For each image, the mean of the model's
output over the mean of the reference in each quartile of the reference's luminance (1.0: unbiased
there). A ratio above 1 in the dim quartiles and below 1 in the brightest is light leaking from
bright into dim regions, which relMSE (weighting dark pixels most) punishes and PSNR barely sees.

    python scripts/brightness_by_quartile.py data/scene_inputs --models layer-medium runs/lm16a_k4.safetensors --spp 4

A spec ``oidn-high`` (or ``oidn-fast``, ``oidn-balanced``) runs OIDN 2.5.1 instead of a model.

``data/scene_inputs`` is where `mcdenoise eval --scenes` keeps the third-party scenes' inputs
(every image folder under a root is read, as eval reads a folder of image folders). Dataset
folders are read by their val split, so the same check runs on our own held-out images:

    python scripts/brightness_by_quartile.py data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val --models layer-medium --spp 4 --summary

``--summary`` ends with, per model, the mean of each quartile's ratio over the images, the lowest
middle-quartile ratio, and on how many images a middle quartile is below ``--floor`` (0.93, the
darkening rule of campaigns 18-19).
"""
from __future__ import annotations

import argparse

import numpy as np

from mcdenoise.eval.images import collect_images
from mcdenoise.eval.methods import Inputs, ModelMethod, OIDNMethod
from mcdenoise.models.weights import load_denoiser


def quartile_ratios(out: np.ndarray, ref: np.ndarray) -> list[float]:
    """Mean luminance of ``out`` over ``ref``'s in each quartile of ``ref``'s luminance; (3, H, W) each."""
    lo, ro = out.mean(0), ref.mean(0)
    q = np.quantile(ro, [0.25, 0.5, 0.75])
    edges = [-np.inf, *q, np.inf]
    ratios = []
    for a, b in zip(edges[:-1], edges[1:]):
        m = (ro > a) & (ro <= b)
        ratios.append(float(lo[m].mean() / max(ro[m].mean(), 1e-12)) if m.any() else float("nan"))
    return ratios


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--models", nargs="+", required=True)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--summary", action="store_true", help="end with each model's means over the images")
    ap.add_argument("--floor", type=float, default=0.93, help="count images whose middle quartiles fall below this")
    ap.add_argument("--self-ensemble", action="store_true",
                    help="run each model as a self-ensemble of 8 orientations (labelled +se), as eval --self-ensemble")
    a = ap.parse_args()
    methods = []
    for spec in a.models:
        if spec.startswith("oidn-"):
            methods.append(OIDNMethod(spec[len("oidn-"):]))
            continue
        m, info = load_denoiser(spec)
        label = info.get("label", spec) + ("+se" if a.self_ensemble else "")
        methods.append(ModelMethod(label, m, info, "cpu", self_ensemble=a.self_ensemble))
    images = [e.folder for e in collect_images(a.roots, split="val")[0]]
    print(f"{a.spp} spp; per model: output/reference mean in the reference's luminance quartiles, dim to bright")
    table: dict[str, list[list[float]]] = {meth.name: [] for meth in methods}
    for im in images:
        ref = im.read_reference(["radiance"])["radiance"]
        x = Inputs(im, a.spp)
        cells = []
        for meth in methods:
            r = quartile_ratios(meth.run(meth.prepare(x)), ref)
            table[meth.name].append(r)
            cells.append(f"{meth.name[:14]:14s} " + " ".join(f"{v:.3f}" for v in r))
        print(f"{im.path.name[:30]:30s} | " + " | ".join(cells))
    if a.summary:
        print(f"summary over {len(images)} images: mean ratio per quartile | lowest middle quartile | images with a middle quartile < {a.floor:g}")
        for name, rows in table.items():
            r = np.array(rows)  # (images, 4); a quartile with no pixels is nan
            mid = r[:, 1:3]
            print(f"{name[:20]:20s} " + " ".join(f"{v:.3f}" for v in np.nanmean(r, 0))
                  + f" | {np.nanmin(mid):.3f} | {int((np.nan_to_num(mid, nan=1.0) < a.floor).any(1).sum())} of {len(rows)}")


if __name__ == "__main__":
    main()
