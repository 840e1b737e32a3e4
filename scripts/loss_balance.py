"""How large is each term of a summed loss on a model's output over training crops? The mean of
each named loss over the crops, and each one's ratio to the first, with the power of two nearest
that ratio: the weight that makes a new term as large as an existing one at the start of a leg
(campaign 30's rule for its tonemapped_l2 weight).

    python scripts/loss_balance.py campaigns/c30/refine_ctx_init.safetensors data/plain_ref,data/detail_ref \
        --terms smape tonemapped_l2 --crop 96 --spp 4 --crops 16
"""
from __future__ import annotations

import argparse
import math

import torch

from mcdenoise.models.weights import load_denoiser
from mcdenoise.train.data import DataConfig, batch_source
from mcdenoise.train.losses import get_loss, input_guide


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", help="shipped name, run folder or .safetensors")
    ap.add_argument("data", help="dataset root(s), comma-separated (train split)")
    ap.add_argument("--terms", nargs="+", required=True, help="registered loss names; ratios are to the first")
    ap.add_argument("--crop", type=int, default=96)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--crops", type=int, default=16)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0, help="the loader's data seed")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    model, info = load_denoiser(a.model)
    cfg = DataConfig(crop=a.crop, batch=a.batch, spp_range=(a.spp, a.spp), workers=0, seed=a.seed)
    source = batch_source(a.data, model, cfg)  # the loader splits "a,b" as --data does
    losses = [get_loss(t) for t in a.terms]
    sums = [0.0] * len(losses)
    steps = math.ceil(a.crops / a.batch)
    with torch.no_grad():
        for t in range(steps):
            batch = source[t]
            pred = model(batch)
            target = batch["target"]
            guide = input_guide(batch["radiance"])
            for i, loss in enumerate(losses):
                sums[i] += float(loss(pred, target, guide)) / steps
    print(f"{info['label']} on {steps * a.batch} crops of {a.data} ({a.crop} px, {a.spp} spp, seed {a.seed}):")
    for loss, v in zip(losses, sums):
        ratio = sums[0] / v if v > 0 else math.inf
        print(f"  {loss.name:16s} mean {v:.6g}   weight making it equal to {losses[0].name}: {ratio:.4g} "
              f"(nearest power of two {2.0 ** round(math.log2(ratio)) if math.isfinite(ratio) else math.inf:g})")


if __name__ == "__main__":
    main()
