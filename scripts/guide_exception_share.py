"""How often does `relmse_in` fall back to the target's weight? For training batches of our own
datasets, the share of pixels (and of the reference's light) where the target is over ``ratio``
times the input's guide, and the share where that changes the weight more than 2x (the
exception's bias matters only there: t / ratio must rival sqrt(0.01)), for the shipped guide,
two floors tried in campaign 18 and `relmse_in_wide`'s ratio (docs/TRAINING.md, "Losses"). Our data
only: the third-party scenes are never read.

    python scripts/guide_exception_share.py data/detail_ref data/detail_ref2 data/detail_ref3 data/rich_ref3 --batches 12 --spp 2 4
"""
from __future__ import annotations

import argparse

import torch
import torch.nn.functional as F

from mcdenoise.models.registry import build_model
from mcdenoise.train.config import TrainConfig
from mcdenoise.train.data import batch_source
from mcdenoise.train.losses import GUIDE_RATIO, RELMSE_EPS, WIDE_GUIDE_RATIO, guided_scale, input_guide
from mcdenoise.train.trainer import data_config


def variants(radiance: torch.Tensor) -> dict[str, tuple[torch.Tensor, float]]:
    """name -> (guide, ratio) for ``radiance (B, S, 3, H, W)``."""
    g = input_guide(radiance)
    mean = radiance.float().mean(1)
    box = F.avg_pool2d(F.pad(mean, (3, 3, 3, 3), mode="replicate"), kernel_size=7, stride=1)
    black = (mean.sum(1, keepdim=True) == 0).expand_as(g)  # every sample black in every channel
    return {
        f"shipped guide, ratio {GUIDE_RATIO:g}": (g, GUIDE_RATIO),
        f"shipped guide, ratio {WIDE_GUIDE_RATIO:g} (relmse_in_wide)": (g, WIDE_GUIDE_RATIO),
        "7x7 box / 8 floor, ratio 30 (layer_m18h)": (torch.maximum(g, box / 8), 30.0),
        f"box / 8 floor on all-black pixels only, ratio {GUIDE_RATIO:g}": (torch.where(black, torch.maximum(g, box / 8), g), GUIDE_RATIO),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="+", help="dataset folders (their train split)")
    ap.add_argument("--batches", type=int, default=12)
    ap.add_argument("--spp", type=int, nargs=2, default=(2, 4), metavar=("LO", "HI"))
    a = ap.parse_args()
    torch.set_num_threads(1)
    model = build_model("layer", "medium")
    cfg = TrainConfig(model="layer", data=",".join(a.data), batch=8, crop=96, spp_range=tuple(a.spp),
                      workers=0).resolved(model.input_kind)
    src = batch_source(a.data, model, data_config(cfg))
    shares: dict[str, list[tuple[float, float, float]]] = {}
    for t in range(a.batches):
        b = src[t]
        target = b["target"]
        for name, (guide, ratio) in variants(b["radiance"]).items():
            hit = target > ratio * guide
            moved = (guided_scale(guide, target, ratio) ** 2 + RELMSE_EPS) > 2 * (guide ** 2 + RELMSE_EPS)
            shares.setdefault(name, []).append((float(hit.float().mean()), float((target * hit).sum() / target.sum()),
                                                float(moved.float().mean())))
    print(f"{a.batches} batches of 8 crops (96 px) at {a.spp[0]}-{a.spp[1]} spp; share of pixels / of the reference's light"
          " where it fires; share of pixels whose weight it moves > 2x")
    for name, v in shares.items():
        px, light, moved = ([row[i] for row in v] for i in range(3))
        print(f"{name:55s} pixels mean {sum(px) / len(px):.3f} max {max(px):.3f} | light mean {sum(light) / len(light):.3f}"
              f" | moved > 2x {sum(moved) / len(moved):.4f}")


if __name__ == "__main__":
    main()
