"""A per-sample model run at two scales, with no training (campaign 28, step 7, docs/TRAINING.md).

The model denoises the image as usual (``full``) and once more at half resolution, where each 2x2
block's samples are merged into one pixel (4x the samples per pixel, sub-pixel positions rescaled
into the larger pixel). The half-resolution output replaces the full one's coarse band:

    out = max(full - up(down(full)) + up(half), 0),   down = 2x2 mean, up = bilinear

so the coarse band comes from a filter with twice the footprint in pixels. Scores ``full`` and
``out`` on each image (relMSE, PSNR) and writes both as EXRs in the layout of ``mcdenoise eval
--save-images`` (``OUT/images/<image>/<k>spp/<method>.exr``), which scripts/error_bands.py reads.

    python scripts/two_scale_probe.py data/scene_inputs --model layer-medium --spp 4 8 16 --out reports/c28_two_scale
"""
from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from mcdenoise.data.channels import base_name
from mcdenoise.data.symmetry import SUBPIXEL
from mcdenoise.eval.images import collect_images
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.io.exr import write_exr
from mcdenoise.models.weights import load_denoiser


def scene_of(image_id: str) -> str:
    """The scene of an image id (``scene_inputs/kitchen_128x128_d8_spp16_seed7`` -> ``kitchen``)."""
    return image_id.rsplit("/", 1)[-1].split("_")[0]


def merge_2x2(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A per-sample batch ``(B, S, C, H, W)`` as the half-resolution image whose pixel holds the
    samples of a 2x2 block: ``(B, 4S, C, H/2, W/2)``; sub-pixel positions ``(x, y)`` become
    ``((x + dx) / 2, (y + dy) / 2)`` in the merged pixel. Non-image entries pass through."""
    out: dict[str, torch.Tensor] = {}
    for name, x in batch.items():
        if not isinstance(x, torch.Tensor) or x.dim() != 5:
            out[name] = x
            continue
        b, s, c, h, w = x.shape
        if h % 2 or w % 2:
            raise ValueError(f"{name}: {h}x{w} is not divisible by 2")
        x = x.reshape(b, s, c, h // 2, 2, w // 2, 2)
        if base_name(name) == SUBPIXEL:
            dy = torch.arange(2, dtype=x.dtype).view(1, 1, 1, 1, 2, 1, 1)
            dx = torch.arange(2, dtype=x.dtype).view(1, 1, 1, 1, 1, 1, 2)
            x = torch.cat([(x[:, :, :1] + dx) / 2, (x[:, :, 1:] + dy) / 2], dim=2)
        # (b, s, c, h2, dy, w2, dx) -> (b, dy, dx, s, c, h2, w2) -> (b, 4s, c, h2, w2)
        out[name] = x.permute(0, 4, 6, 1, 2, 3, 5).reshape(b, 4 * s, c, h // 2, w // 2).contiguous()
    return out


def two_scale(full: np.ndarray, half: np.ndarray) -> np.ndarray:
    """``full (3, H, W)`` with its 2x2-mean band replaced by ``half (3, H/2, W/2)``, clamped at 0."""
    f = torch.from_numpy(np.ascontiguousarray(full, dtype=np.float32))[None]
    hf = torch.from_numpy(np.ascontiguousarray(half, dtype=np.float32))[None]
    size = f.shape[-2:]
    coarse_full = F.interpolate(F.avg_pool2d(f, 2), size=size, mode="bilinear", align_corners=False)
    coarse_half = F.interpolate(hf, size=size, mode="bilinear", align_corners=False)
    return (f - coarse_full + coarse_half).clamp_min(0.0)[0].numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--model", default="layer-medium")
    ap.add_argument("--spp", nargs="+", type=int, default=[4, 8, 16])
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    images, _ = collect_images(a.roots, split=a.split)
    model, info = load_denoiser(a.model)
    meth = ModelMethod(a.model, model, info, "cpu")
    rows: dict[int, list[tuple[str, float, float, float, float]]] = collections.defaultdict(list)
    for e in images:
        ref = e.folder.read_reference(["radiance"])["radiance"]
        folder = a.out / "images" / e.id
        write_exr(folder / "reference.exr", {"radiance": ref})
        for spp in a.spp:
            batch = meth.prepare(Inputs(e.folder, spp))
            with torch.inference_mode():
                full = meth.run(batch)
                half = meth.run(merge_2x2(batch))
            out = two_scale(full, half)
            write_exr(folder / f"{spp}spp" / f"{a.model}.exr", {"radiance": full})
            write_exr(folder / f"{spp}spp" / "two-scale.exr", {"radiance": out})
            rows[spp].append((e.id, relmse(full, ref), psnr(full, ref), relmse(out, ref), psnr(out, ref)))
            print(f"{e.id} {spp} spp: {a.model} {rows[spp][-1][1]:.5f} / {rows[spp][-1][2]:.3f}  "
                  f"two-scale {rows[spp][-1][3]:.5f} / {rows[spp][-1][4]:.3f}", flush=True)
    for spp, r in sorted(rows.items()):
        v = np.array([x[1:] for x in r])
        print(f"{spp:2d} spp, {len(r)} images: {a.model} relMSE {v[:, 0].mean():.5f} PSNR {v[:, 1].mean():.4f} | "
              f"two-scale relMSE {v[:, 2].mean():.5f} PSNR {v[:, 3].mean():.4f} | ratio {v[:, 2].mean() / v[:, 0].mean():.4f}")
        scenes = sorted({scene_of(i) for i, *_ in r})
        per = []
        for s in scenes:
            sv = np.array([x[1:] for x in r if scene_of(x[0]) == s])
            per.append(f"{s} {sv[:, 2].mean() / sv[:, 0].mean():.3f}")
        print("    two-scale / full, mean relMSE per scene: " + " ".join(per))


if __name__ == "__main__":
    main()
