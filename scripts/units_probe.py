"""Probe (issue 19): how much the models depend on the scene's units and exposure.

``--what depth``: every depth-like input (``depth``, ``depth_diffuse``, their variances, the
camera's focus distance and aperture radius) is multiplied by a factor before the model runs; a
model that reads depth in world units gives other images for the same picture in centimetres and
in metres. ``median`` rescales each image so its median first-hit depth is ``--median`` units.

``--what radiance``: every radiance-like input (``radiance``, ``diffuse``, ``specular``; variances
by the square) is multiplied by the factor and the output divided by it, as a change of exposure
would; ``median`` brings the image's median pixel luminance to ``--median``.

relMSE and PSNR against each folder's reference; inputs are the first ``spp`` samples.

    python scripts/units_probe.py data/scene_inputs --models sbmc wskp kpcn-pixel --scales 1 0.1 10 median
    python scripts/units_probe.py data/scene_inputs --what radiance --median 0.1 --models sbmc --scales 1 0.1 median
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.models.weights import load_denoiser

#: Inputs in world units of length, and the power of the scale each carries.
LENGTHS = {"depth": 1, "depth_diffuse": 1, "depth_variance": 2, "depth_diffuse_variance": 2}
#: Inputs in units of radiance, and their power.
RADIANCES = {"radiance": 1, "diffuse": 1, "specular": 1, "radiance_variance": 2, "diffuse_variance": 2,
             "specular_variance": 2}
#: scene_features entries in world units: aperture_radius, focus_distance (see SCENE_FEATURES).
SCENE_LENGTH_IDX = (1, 2)


def scaled(batch: dict[str, torch.Tensor], s: float, what: str) -> dict[str, torch.Tensor]:
    out = dict(batch)
    for k, p in (LENGTHS if what == "depth" else RADIANCES).items():
        if k in out:
            out[k] = out[k] * s ** p
    if what == "depth" and "scene_features" in out:
        sf = out["scene_features"].clone()
        sf[..., list(SCENE_LENGTH_IDX)] *= s
        out["scene_features"] = sf
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("roots", nargs="+", help="image folders under these; a dataset (manifest.json) gives its val split")
    ap.add_argument("--models", nargs="+", required=True)
    ap.add_argument("--spp", nargs="+", type=int, default=[8])
    ap.add_argument("--scales", nargs="+", default=["1", "median"])
    ap.add_argument("--what", choices=["depth", "radiance"], default="depth")
    ap.add_argument("--median", type=float, default=3.0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    folders = []
    for root in map(Path, a.roots):
        if (root / "manifest.json").is_file():  # a dataset: its val split only (never what was trained on)
            from mcdenoise.data.dataset import Dataset

            folders += [im.path for im in Dataset(root).images("val") if im.has_reference]
        else:
            folders += [m.parent for m in sorted(root.rglob("meta.json")) if (m.parent / "reference.exr").is_file()]
    methods = [ModelMethod(n, *load_denoiser(n), device="cpu") for n in a.models]
    for spp in a.spp:
        meds = []
        res = {(m.name, s): [] for m in methods for s in a.scales}
        for f in folders:
            im = ImageFolder(f)
            if im.samples is None and im.meta.spp != spp:  # a pixel-only image counts at its own spp only
                continue
            ref = im.read_reference(["radiance"])["radiance"]
            x = Inputs(im, spp)
            if a.what == "depth":
                d = x.model_inputs(["depth"], "pixels")["depth"]
                med = float(np.median(d[d > 0])) if (d > 0).any() else 1.0
            else:
                med = max(float(np.median(x.radiance.mean(axis=0))), 1e-6)
            for m in methods:
                batch = m.prepare(x)
                for s in a.scales:
                    fac = a.median / med if s == "median" else float(s)
                    with torch.inference_mode():
                        out = m.model(scaled(batch, fac, a.what))[0].float().numpy()
                    if a.what == "radiance":
                        out = out / fac
                    res[(m.name, s)].append((f.name.split("_")[0], relmse(out, ref), psnr(out, ref)))
        for (name, s), rows in res.items():
            r = np.array([v[1] for v in rows]); p = np.array([v[2] for v in rows])
            per = " ".join(f"{n} {v:.3f}" for n, v, _ in rows)
            print(f"spp {spp:2d} {name:12s} scale {s:>6s}: relMSE {r.mean():.4f} (geometric mean {np.exp(np.log(r).mean()):.4f}) "
                  f"PSNR {p.mean():.2f} | {per}", flush=True)


if __name__ == "__main__":
    main()
