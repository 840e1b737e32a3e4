"""Start a combiner with a kernel-model candidate from shipped weights (issue 20): the weight network
of a shipped combiner where its tensors fit, the new candidate's inputs and output at zero (so the
start is the shipped combiner's choice, the kernel candidate at a low logit), and the kernel model
itself from its shipped weights, frozen.

    python scripts/combine_kernel_init.py combine-ens kpcn-pixel campaigns/c10/combine_ens_kpcn_init.safetensors \
        --preset ens_kpcn --set shrink=1.0

With ``--fresh`` the weight network is a new one (the identity start on OIDN) and the combiner
argument only gives the configuration:

    python scripts/combine_kernel_init.py combine-ens kpcn-pixel campaigns/c10/combine_kpcn_init.safetensors \
        --preset kpcn --fresh --set shrink=1.0 prefiltered=false

The new first-layer input channels (the candidate's log colour and deviation from OIDN) come last
and start at zero; the candidate's weight logit is the noisy candidate's bias (its output channel
is the last). Prints what was copied.
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
    ap.add_argument("combiner", help="shipped combiner name or .safetensors")
    ap.add_argument("kernel", help="shipped pixel model name or .safetensors (the candidate)")
    ap.add_argument("dst")
    ap.add_argument("--preset", default="ens_kpcn")
    ap.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--fresh", action="store_true", help="a new weight network (identity start on OIDN)")
    a = ap.parse_args()
    cmeta, cten = read_weights(a.combiner)
    kmeta, kten = read_weights(a.kernel)
    cfg = json.loads(cmeta["model_config"])
    cfg.update(kernel_candidate=f"{kmeta['model']}:{kmeta['preset']}", kernel_candidate_config=json.loads(kmeta["model_config"]))
    cfg = apply_sets(cfg, a.set)
    model = model_from_config("combine", a.preset, cfg)
    state = model.state_dict()
    out_ch = model.net.final.weight.shape[0]
    for k, t in state.items():
        if k.startswith("kernel_model."):
            state[k] = kten[k.removeprefix("kernel_model.")].clone()
            continue
        if a.fresh:
            continue
        old = cten[k]
        if old.shape == t.shape:
            state[k] = old.clone()
            continue
        new = torch.zeros_like(t)
        new[tuple(slice(0, n) for n in old.shape)] = old  # new input/output channels come last
        if k == "net.final.bias":  # the kernel candidate starts at the noisy candidate's logit
            new[old.shape[0]:] = old[old.shape[0] - 1]
        state[k] = new
        print(f"{k}: {tuple(old.shape)} -> {tuple(t.shape)}")
    model.load_state_dict(state, strict=True)
    meta = {"model": "combine", "preset": a.preset, "model_config": json.dumps(cfg), "step": "0"}
    save_file({k: v.contiguous() for k, v in state.items()}, a.dst, metadata=meta)
    load_denoiser(a.dst)  # refuses anything that would not load back
    print(f"wrote {a.dst}: combine ({a.preset}), {out_ch} weight channels, kernel candidate {cfg['kernel_candidate']}")


if __name__ == "__main__":
    main()
