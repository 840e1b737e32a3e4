"""Where a model's relMSE on one image comes from: its worst pixels, their share of the error, and
the inputs there (how wskp's window-edge row on salle-de-bain was found, docs/TRAINING.md campaign 3).

    python scripts/worst_pixels.py wskp data/scene_inputs/salle-de-bain_128x128_d8_spp16_seed7 --spp 8
    python scripts/worst_pixels.py layer-medium data/scene_inputs/bathroom_128x128_d8_spp16_seed7 --spp 4

Pixel models run through ``mcdenoise.denoise`` on the pixel means; per-sample models read the
folder's first ``--spp`` samples, as ``mcdenoise eval`` gives them.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

import mcdenoise
from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.data.tensors import image_batch
from mcdenoise.data.stats import pixel_stats
from mcdenoise.eval.metrics import relmse
from mcdenoise.models.weights import load_denoiser


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("model", help="a shipped model name, weights file or run folder")
    ap.add_argument("folder", help="an image folder with samples and reference.exr")
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--top", type=int, default=10)
    a = ap.parse_args()
    f = ImageFolder(a.folder)
    ref = f.read_reference(["radiance"])["radiance"]
    smp = f.samples.read(["radiance", "albedo", "normal", "depth"], samples=list(range(a.spp)))
    m = {c: pixel_stats(v)[0] for c, v in smp.items()}
    net, _ = load_denoiser(a.model)
    if net.input_kind == "samples":
        batch = image_batch(f, net.required_channels(), "samples", samples=slice(0, a.spp))
        with torch.no_grad():
            out = net(batch)[0].numpy()
    else:
        out = mcdenoise.denoise(m["radiance"], albedo=m["albedo"], normal=m["normal"], depth=m["depth"], model=net)
    # per-pixel relMSE (the metric's form and epsilon): the image's relMSE is the mean of this map
    err = ((out - ref) ** 2 / (ref ** 2 + 1e-2)).mean(0)
    print(f"relMSE {relmse(out, ref):.4g} (noisy {relmse(m['radiance'], ref):.4g}); "
          f"the worst 100 pixels hold {np.sort(err.ravel())[::-1][:100].sum() / err.sum():.0%} of the error")
    for i in np.argsort(err.ravel())[::-1][:a.top]:
        y, x = divmod(int(i), err.shape[1])
        print(f"  ({y}, {x}) out {out[:, y, x].round(3)} ref {ref[:, y, x].round(3)} noisy {m['radiance'][:, y, x].round(3)} "
              f"albedo {m['albedo'][:, y, x].round(2)} |normal| {np.linalg.norm(m['normal'][:, y, x]):.2f}")


if __name__ == "__main__":
    main()
