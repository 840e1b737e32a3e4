"""Does test-time self-ensembling pay for a kernel model? Each image is denoised as it is and in
the other 7 orientations of the square's symmetry group (rotations by 90 degrees, with and
without a mirror); the outputs, turned back, are averaged over 4 (no rotation and 180 degrees,
each with and without the mirror) and over all 8. Prints relMSE and PSNR per image and the means.

    python scripts/self_ensemble_probe.py data/scene_inputs --model layer-medium --spp 4

Averaging orientations reduces the variance of the predicted kernels, not their bias: it costs
4x or 8x the model's time.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from mcdenoise.data.tensors import image_batch
from mcdenoise.eval.images import collect_images
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.models.weights import load_denoiser


def orient(t: torch.Tensor, k: int, inverse: bool = False) -> torch.Tensor:
    """Orientation ``k`` in 0..7 of ``t``'s last two axes (k % 4 quarter turns after a mirror when k >= 4)."""
    turns, mirror = k % 4, k >= 4
    if inverse:
        t = torch.rot90(t, -turns, dims=(-2, -1))
        return t.flip(-1) if mirror else t
    if mirror:
        t = t.flip(-1)
    return torch.rot90(t, turns, dims=(-2, -1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--model", required=True)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    model, _ = load_denoiser(a.model)
    images = [e.folder for e in collect_images(a.roots, split="val")[0]]
    rows = []
    print(f"{a.model}, {a.spp} spp: relMSE one / 4 / 8 orientations | PSNR one / 4 / 8")
    for im in images:
        ref = np.asarray(im.read_reference(["radiance"])["radiance"])
        batch = image_batch(im, model.required_channels(), model.input_kind, samples=slice(0, a.spp))
        outs = []
        with torch.no_grad():
            for k in range(8):  # image tensors have >= 4 axes; scene_features (B, F) stay as they are
                bk = {n: orient(v, k) if v.dim() >= 4 else v for n, v in batch.items()}
                outs.append(orient(model(bk), k, inverse=True)[0])
        ests = [outs[0], torch.stack([outs[i] for i in (0, 2, 4, 6)]).mean(0), torch.stack(outs).mean(0)]
        ests = [e.numpy() for e in ests]
        r = [float(relmse(e, ref)) for e in ests] + [float(psnr(e, ref)) for e in ests]
        rows.append(r)
        print(f"{im.path.name[:30]:30s} " + " ".join(f"{v:.4f}" for v in r[:3]) + " | " + " ".join(f"{v:.2f}" for v in r[3:]))
    m = np.mean(rows, 0)
    print(f"{'mean':30s} " + " ".join(f"{v:.4f}" for v in m[:3]) + " | " + " ".join(f"{v:.2f}" for v in m[3:]))


if __name__ == "__main__":
    main()
