"""Does a sample model lose to OIDN because its per-sample guides are noisy? Campaign 34's check.

For each image folder, the model denoises the first 4 samples twice: as stored, and with the
per-sample guides (albedo and normal; then depth and roughness too) replaced by their means over
every stored sample, broadcast to each of the 4 (4x less guide noise at 16 stored spp, the radiance
untouched). Prints relMSE against the reference for each, and the ratio to the stored run.

    python scripts/guide_swap_probe.py layer-medium data/scene_inputs/{teapot,coffee,lamp,car2,teapot-full}_128x128_d8_spp16_seed7

Campaign 34: under 1% either way on those five product shots, so the guides' noise is not their gap.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from mcdenoise.data.image_folder import read_image
from mcdenoise.data.tensors import input_arrays
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.metrics import relmse
from mcdenoise.models.weights import load_denoiser

SWAPS = (("albedo", "normal"), ("albedo", "normal", "depth", "roughness"))


def swap_to_means(batch: dict[str, torch.Tensor], full: dict[str, np.ndarray], channels: tuple[str, ...]) -> dict[str, torch.Tensor]:
    """``batch``'s per-sample ``channels`` (1, k, C, H, W) replaced by the mean of ``full`` (S, C, H, W)
    over its S samples, repeated k times; every other entry as it was (the same tensors)."""
    out = dict(batch)
    for c in channels:
        mean = torch.from_numpy(np.ascontiguousarray(full[c].mean(0, keepdims=True)))
        out[c] = mean.to(batch[c].dtype).expand_as(batch[c][0])[None].contiguous()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", help="a sample model: registered name, run folder or .safetensors")
    ap.add_argument("folders", nargs="+", type=Path, help="image folders with per-sample data and a reference")
    ap.add_argument("--spp", type=int, default=4)
    a = ap.parse_args()
    model, info = load_denoiser(a.model)
    m = ModelMethod("m", model, info, "cpu")
    if m.model.input_kind != "samples":
        ap.error(f"{a.model}: not a sample model")
    for f in a.folders:
        fo = read_image(f)
        ref = fo.read_reference()["radiance"]
        batch = m.prepare(Inputs(fo, a.spp))
        base = relmse(m.run(batch), ref)
        full = input_arrays(fo, sorted({c for s in SWAPS for c in s}), "samples", spp=fo.meta.spp)
        cells = [f"stored {base:.4f}"]
        for swap in SWAPS:
            r = relmse(m.run(swap_to_means(batch, full, swap)), ref)
            cells.append(f"{'+'.join(swap)} means {r:.4f} ({r / base:.3f})")
        print(f"{f.name:45s} " + "  ".join(cells), flush=True)


if __name__ == "__main__":
    main()
