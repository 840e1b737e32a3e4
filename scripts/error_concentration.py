"""How concentrated a method's relMSE is on one image: the share of its worst 100 pixels, of the
pixels whose samples are all black, of overshoots, and its relMSE without the worst 100 pixels
(campaign 23: are we behind OIDN in a few halos or everywhere?).

    python scripts/error_concentration.py layer-medium data/scene_inputs/bathroom_128x128_d8_spp16_seed7 --spp 4

A model (shipped name, run folder or weights) is compared with OIDN 2.5.1 high and the noisy mean on
the folder's first ``--spp`` samples, as ``mcdenoise eval`` gives them.
"""
from __future__ import annotations

import argparse

import numpy as np

import mcdenoise  # noqa: F401  (sets up the package's defaults)
from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.oidn import oidn_denoise
from mcdenoise.models.weights import load_denoiser

EPS = 0.01  # the relMSE's, mcdenoise/eval/metrics.py
TOP = 100


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("folders", nargs="+", help="image folders with samples and a reference")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    net, info = load_denoiser(a.model)
    method = ModelMethod(info.get("label", a.model), net, info, "cpu")
    for folder in a.folders:
        im = ImageFolder(folder)
        ref = im.read_reference(["radiance"])["radiance"]
        x = Inputs(im, a.spp)
        mu = x.guides["radiance"]
        outs = {method.name: method.run(method.prepare(x)),
                "oidn-high": oidn_denoise(mu, x.guides["albedo"], x.guides["normal"], threads=a.threads),
                "noisy": mu}
        black = mu.max(axis=0) == 0
        print(f"{folder} at {a.spp} spp ({black.mean():.3f} of the pixels have only black samples):")
        for name, y in outs.items():
            e = ((y - ref) ** 2 / (ref**2 + EPS)).mean(axis=0)
            worst = np.sort(e.ravel())[::-1][:TOP].sum()
            over = y.mean(axis=0) > ref.mean(axis=0)
            print(f"  {name:14s} relMSE {e.mean():.4f}  worst {TOP} px {worst / e.sum():.2f}  black-sample px "
                  f"{e[black].sum() / e.sum():.2f}  overshoots {e[over].sum() / e.sum():.2f}  "
                  f"relMSE without the worst {TOP} {(e.sum() - worst) / e.size:.4f}")


if __name__ == "__main__":
    main()
