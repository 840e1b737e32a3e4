"""Time a combiner at 1920x1080 piece by piece beside OIDN high (issue 20's 0.5x).

    python scripts/lite_cost_probe.py --preset own --reps 5
    python scripts/lite_cost_probe.py --kpcn layers=3 channels=16 conv_size=3 kernel_size=5 --reps 3

Prints median ms and the ratio to OIDN 2.5.1 high (same threads) of: with ``--preset kpcn``, the
kernel model's features, each branch's trunk and the whole kernel model (kpcn ``pixel`` with the
``--kpcn`` fields over it); then the combiner's features, its weight network and the whole
combiner. Models run as inference runs them (bfloat16 trunks where the CPU has them natively).
Random inputs and weights: the cost does not depend on the values.
"""
from __future__ import annotations

import argparse

import torch

from mcdenoise.bench.timing import median_time
from mcdenoise.eval.oidn import oidn_denoise
from mcdenoise.models.base import build_from_fields
from mcdenoise.models.builtin import load_builtin_models
from mcdenoise.models.inference import inference_context, prepare_inference
from reconfigure_weights import apply_sets  # scripts/ is on the path when a script runs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kpcn", nargs="*", default=[], help="kpcn:pixel fields FIELD=VALUE over the preset (--preset kpcn)")
    ap.add_argument("--combine", nargs="*", default=[], help="combiner fields FIELD=VALUE over the preset")
    ap.add_argument("--preset", default="kpcn", help="combiner preset (kpcn: with the kernel model above)")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    load_builtin_models()
    w, h = map(int, args.size.split("x"))
    g = torch.Generator().manual_seed(0)
    batch = {n: torch.rand(1, 3, h, w, generator=g) for n in ("diffuse", "specular", "albedo", "normal", "oidn", "radiance")}
    batch["depth"] = torch.rand(1, 1, h, w, generator=g) * 10
    kfields = apply_sets({}, args.kpcn)
    cfields = apply_sets({}, args.combine)
    km = None
    if args.preset == "kpcn":
        km = prepare_inference(build_from_fields("kpcn", "pixel", kfields), precision="auto")
        cfields["kernel_candidate_config"] = kfields
    cm = prepare_inference(build_from_fields("combine", args.preset, cfields), precision="auto")

    def ms(fn) -> float:
        return median_time(fn, args.reps, warmup=1) * 1e3

    col, alb, nrm = (batch["diffuse"] + batch["specular"])[0].numpy(), batch["albedo"][0].numpy(), batch["normal"][0].numpy()
    rows = [("oidn high", ms(lambda: oidn_denoise(col, alb, nrm, quality="high", threads=args.threads)))]
    with inference_context():
        if km is not None:
            feats = km.features(batch)
            rows.append(("kpcn features", ms(lambda: km.features(batch))))
            for name, x in feats.items():
                rows.append((f"trunk {name}", ms(lambda x=x, name=name: km.branches[name](x))))
            rows.append(("kernel model", ms(lambda: km(batch))))
        kernel = cm.kernel_output(batch)  # None without a kernel model
        f = cm.features(batch, kernel)
        rows.append(("combiner features", ms(lambda: cm.features(batch, kernel))))
        rows.append(("combiner weight net", ms(lambda: cm.net(f))))
        rows.append((f"combine:{args.preset} whole", ms(lambda: cm(batch))))
    base = rows[0][1]
    params = sum(p.numel() for p in cm.parameters())
    print(f"combine:{args.preset} {cfields} ({params} parameters, kernel model included); {args.size}, "
          f"{args.threads} threads, medians of {args.reps}")
    for name, t in rows:
        print(f"{name:28s} {t:9.1f} ms  {t / base:6.3f}x OIDN high")


if __name__ == "__main__":
    main()
