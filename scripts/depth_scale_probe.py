"""Probe (issue 19): how much the models depend on the scene's units. Every depth-like input
(``depth``, ``depth_diffuse``, their variances, the camera's focus distance and aperture radius)
is multiplied by a factor before the model runs; a model that reads depth in world units gives
other images for the same picture in centimetres and in metres. ``median`` rescales each image so
its median first-hit depth is ``--median`` units (the procedural world's typical scale).

relMSE and PSNR against each folder's reference; inputs are the first ``spp`` samples.

    python scripts/depth_scale_probe.py data/scene_inputs --models sbmc wskp kpcn-pixel --scales 1 0.1 10 median
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
#: scene_features entries in world units: aperture_radius, focus_distance (see SCENE_FEATURES).
SCENE_LENGTH_IDX = (1, 2)


def scaled(batch: dict[str, torch.Tensor], s: float) -> dict[str, torch.Tensor]:
    out = dict(batch)
    for k, p in LENGTHS.items():
        if k in out:
            out[k] = out[k] * s ** p
    if "scene_features" in out:
        sf = out["scene_features"].clone()
        sf[..., list(SCENE_LENGTH_IDX)] *= s
        out["scene_features"] = sf
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--models", nargs="+", required=True)
    ap.add_argument("--spp", nargs="+", type=int, default=[8])
    ap.add_argument("--scales", nargs="+", default=["1", "median"])
    ap.add_argument("--median", type=float, default=3.0)
    a = ap.parse_args()
    torch.set_num_threads(1)
    folders = [m.parent for r in map(Path, a.roots) for m in sorted(r.rglob("meta.json")) if (m.parent / "reference.exr").is_file()]
    methods = [ModelMethod(n, *load_denoiser(n), device="cpu") for n in a.models]
    for spp in a.spp:
        res = {(m.name, s): [] for m in methods for s in a.scales}
        for f in folders:
            im = ImageFolder(f)
            ref = im.read_reference(["radiance"])["radiance"]
            x = Inputs(im, spp)
            d = x.model_inputs(["depth"], "pixels")["depth"]
            med = float(np.median(d[d > 0])) if (d > 0).any() else 1.0
            for m in methods:
                batch = m.prepare(x)
                for s in a.scales:
                    fac = a.median / med if s == "median" else float(s)
                    with torch.inference_mode():
                        out = m.model(scaled(batch, fac))[0].float().numpy()
                    res[(m.name, s)].append((f.name.split("_")[0], relmse(out, ref), psnr(out, ref)))
        for (name, s), rows in res.items():
            r = np.array([v[1] for v in rows]); p = np.array([v[2] for v in rows])
            per = " ".join(f"{n} {v:.3f}" for n, v, _ in rows)
            print(f"spp {spp:2d} {name:12s} scale {s:>6s}: relMSE {r.mean():.4f} PSNR {p.mean():.2f} | {per}", flush=True)


if __name__ == "__main__":
    main()
