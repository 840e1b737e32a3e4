"""Start a second stage (``refine``, campaign 29) over a shipped or saved model: the base from its
weights, frozen, and a fresh head that starts as (nearly) the identity on the base's output.

    python scripts/refine_init.py layer-medium campaigns/c29/refine_init.safetensors --preset layer_medium

The base's configuration is its card's (or file's) ``model_config``, stored in the new file's, so
the file alone rebuilds both. Prints what it wrote; refuses a file that would not load back.
"""
from __future__ import annotations

import argparse
import json

import torch
from safetensors.torch import save_file

from mcdenoise.models.weights import load_denoiser, model_from_config
from reconfigure_weights import apply_sets, read_weights  # scripts/ is on the path when a script runs



def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base", help="shipped model name (layer-medium) or .safetensors")
    ap.add_argument("dst")
    ap.add_argument("--preset", default="layer_medium")
    ap.add_argument("--seed", type=int, default=0, help="seed of the fresh head's initialisation")
    ap.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE", help="refine config fields")
    a = ap.parse_args()
    bmeta, bten = read_weights(a.base)
    cfg = {"base": f"{bmeta['model']}:{bmeta['preset']}", "base_config": json.loads(bmeta["model_config"])}
    cfg = apply_sets(cfg, a.set)
    torch.manual_seed(a.seed)
    model = model_from_config("refine", a.preset, cfg)
    state = model.state_dict()
    for k in state:
        if k.startswith("base."):
            state[k] = bten[k.removeprefix("base.")].clone()
    model.load_state_dict(state, strict=True)
    meta = {"model": "refine", "preset": a.preset, "model_config": json.dumps(cfg), "step": "0"}
    save_file({k: v.contiguous() for k, v in state.items()}, a.dst, metadata=meta)
    load_denoiser(a.dst)  # refuses anything that would not load back
    head = sum(p.numel() for n, p in model.named_parameters() if not n.startswith("base."))
    print(f"wrote {a.dst}: refine ({a.preset}) over {cfg['base']}, head {head:,} parameters, base frozen")


if __name__ == "__main__":
    main()
