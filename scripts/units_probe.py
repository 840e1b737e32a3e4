"""Probe (issue 19): how much the models depend on the scene's units and exposure.

``--what depth``: every depth-like input (``depth``, ``depth_diffuse``, their variances, the
camera's focus distance and aperture radius) is multiplied by a factor before the model runs; a
model that reads depth in world units gives other images for the same picture in centimetres and
in metres. ``median`` rescales each image so its median first-hit depth is ``--median`` units.

``--what radiance``: every radiance-like input (``radiance``, ``diffuse``, ``specular``; variances
by the square) is multiplied by the factor and the output divided by it, as a change of exposure
would; ``median`` brings the image's median pixel luminance to ``--median``.

relMSE and PSNR against each folder's reference; inputs are the first ``spp`` samples. A dataset
gives its ``--split`` (default val: never what was trained on).

``--stats`` runs no model: per root, the 5th/50th/95th percentiles over images of the median
first-hit depth, the median pixel luminance, and the autoexposure's block-luminance geometric mean
``L`` (:mod:`mcdenoise.models.exposure`) of the ``spp``-sample mean.

    python scripts/units_probe.py data/scene_inputs --models sbmc wskp kpcn-pixel --scales 1 0.1 10 median
    python scripts/units_probe.py data/scene_inputs --what radiance --median 0.1 --models sbmc --scales 1 0.1 median
    python scripts/units_probe.py data/scene_inputs data/detail_ref data/rich_ref4 --split train --stats --spp 16
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from mcdenoise.eval.images import collect_images
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.models.exposure import autoexposure_scale, scale_batch
from mcdenoise.models.weights import load_denoiser

#: Inputs in world units of length, and the power of the scale each carries.
LENGTHS = {"depth": 1, "depth_diffuse": 1, "depth_variance": 2, "depth_diffuse_variance": 2}
#: scene_features entries in world units: aperture_radius, focus_distance (see SCENE_FEATURES).
SCENE_LENGTH_IDX = (1, 2)


def scaled(batch: dict[str, torch.Tensor], s: float, what: str) -> dict[str, torch.Tensor]:
    if what == "radiance":
        return scale_batch(batch, torch.tensor([s]))
    out = dict(batch)
    for k, p in LENGTHS.items():
        if k in out:
            out[k] = out[k] * s ** p
    if "scene_features" in out:
        sf = out["scene_features"].clone()
        sf[..., list(SCENE_LENGTH_IDX)] *= s
        out["scene_features"] = sf
    return out


def median_depth(x: Inputs) -> float:
    d = x.model_inputs(["depth"], "pixels")["depth"]
    return float(np.median(d[d > 0])) if (d > 0).any() else 1.0


def median_luminance(x: Inputs) -> float:
    return max(float(np.median(x.radiance.mean(axis=0))), 1e-6)


def stats(roots: list[str], split: str, spp: int) -> None:
    for root in roots:
        rows = []
        for im in collect_images([root], split)[0]:
            if im.folder.samples is None and im.folder.meta.spp != spp:
                continue
            x = Inputs(im.folder, spp)
            lum = 1.0 / float(autoexposure_scale(torch.from_numpy(x.radiance)[None], 1.0)[0])
            rows.append((median_depth(x), median_luminance(x), lum))
        q = np.percentile(np.array(rows), [5, 50, 95], axis=0)
        names = ("median depth", "median luminance", "L")
        print(f"{root} ({len(rows)} images, {spp} spp) 5th / 50th / 95th percentiles: " + "; ".join(
            f"{n} {q[0, i]:.3g} / {q[1, i]:.3g} / {q[2, i]:.3g}" for i, n in enumerate(names)), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("roots", nargs="+", help="datasets, image folders, or folders of image folders")
    ap.add_argument("--split", default="val", help="the split a dataset gives (default val)")
    ap.add_argument("--models", nargs="+", default=[])
    ap.add_argument("--spp", nargs="+", type=int, default=[8])
    ap.add_argument("--scales", nargs="+", default=["1", "median"])
    ap.add_argument("--what", choices=["depth", "radiance"], default="depth")
    ap.add_argument("--median", type=float, default=3.0)
    ap.add_argument("--stats", action="store_true", help="only the depth and brightness statistics of the images")
    a = ap.parse_args()
    torch.set_num_threads(1)
    if a.stats:
        stats(a.roots, a.split, a.spp[0])
        return
    if not a.models:
        ap.error("give --models (or --stats)")
    images = collect_images(a.roots, a.split)[0]
    methods = [ModelMethod(n, *load_denoiser(n), device="cpu") for n in a.models]
    for spp in a.spp:
        res = {(m.name, s): [] for m in methods for s in a.scales}
        for im in images:
            f = im.folder
            if f.samples is None and f.meta.spp != spp:  # a pixel-only image counts at its own spp only
                continue
            ref = f.read_reference(["radiance"])["radiance"]
            x = Inputs(f, spp)
            med = median_depth(x) if a.what == "depth" else median_luminance(x)
            for m in methods:
                batch = m.prepare(x)
                for s in a.scales:
                    fac = a.median / med if s == "median" else float(s)
                    with torch.inference_mode():
                        out = m.model(scaled(batch, fac, a.what))[0].float().numpy()
                    if a.what == "radiance":
                        out = out / fac
                    res[(m.name, s)].append((f.path.name.split("_")[0], relmse(out, ref), psnr(out, ref)))
        for (name, s), rows in res.items():
            r = np.array([v[1] for v in rows]); p = np.array([v[2] for v in rows])
            per = " ".join(f"{n} {v:.3f}" for n, v, _ in rows)
            print(f"spp {spp:2d} {name:12s} scale {s:>6s}: relMSE {r.mean():.4f} (geometric mean {np.exp(np.log(r).mean()):.4f}) "
                  f"PSNR {p.mean():.2f} | {per}", flush=True)


if __name__ == "__main__":
    main()
