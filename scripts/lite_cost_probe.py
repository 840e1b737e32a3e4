"""Time a kernel candidate and a combiner around it at 1920x1080, piece by piece (issue 20's 1.5x).

    python scripts/lite_cost_probe.py --kpcn layers=3 channels=16 conv_size=3 kernel_size=5 --reps 3

Prints median ms of: OIDN high (pyoidn, same threads), the kpcn features, each branch's trunk,
the kernel application, the whole kernel model, and the whole combiner (``kpcn`` preset with that
candidate), each in the precision inference uses (bfloat16 trunks where native). Random inputs:
the cost does not depend on the values.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from mcdenoise.models.base import build_from_fields
from mcdenoise.models.inference import inference_context, prepare_inference
from mcdenoise.models.builtin import load_builtin_models


def _parse(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, v = it.split("=", 1)
        out[k] = int(v) if v.lstrip("-").isdigit() else (float(v) if v.replace(".", "", 1).isdigit() else v)
    return out


def _time(fn, reps: int) -> float:
    fn()
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kpcn", nargs="*", default=[], help="kpcn:pixel config fields over the preset (k=v)")
    ap.add_argument("--combine", nargs="*", default=[], help="combiner config fields over the preset")
    ap.add_argument("--preset", default="kpcn", help="combiner preset (kpcn: with the kernel model above; own: none)")
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
    kfields = _parse(args.kpcn)
    km = prepare_inference(build_from_fields("kpcn", "pixel", kfields), precision="auto")
    cfields = _parse(args.combine)
    if args.preset == "kpcn":
        cfields["kernel_candidate_config"] = kfields
    cm = prepare_inference(build_from_fields("combine", args.preset, cfields), precision="auto")
    from mcdenoise.eval.oidn import oidn_denoise

    rows = []
    col, alb, nrm = ((batch["diffuse"] + batch["specular"])[0].numpy(), batch["albedo"][0].numpy(), batch["normal"][0].numpy())
    rows.append(("oidn high", _time(lambda: oidn_denoise(col, alb, nrm, quality="high", threads=args.threads), args.reps)))
    with inference_context():
        if args.preset == "kpcn":
            feats = km.features(batch)
            rows.append(("kpcn features", _time(lambda: km.features(batch), args.reps)))
            for name, x in feats.items():
                rows.append((f"trunk {name}", _time(lambda x=x, name=name: km.branches[name](x), args.reps)))
            rows.append(("kernel model", _time(lambda: km(batch), args.reps)))
        f = cm.features(batch)
        rows.append(("combiner features", _time(lambda: cm.features(batch), args.reps)))
        rows.append(("combiner weight net", _time(lambda: cm.net(f), args.reps)))
        rows.append((f"combine:{args.preset} whole", _time(lambda: cm(batch), args.reps)))
    base = rows[0][1]
    params = sum(p.numel() for p in km.parameters())
    print(f"combine:{args.preset} {cfields}, kpcn fields {kfields} ({params} parameters); {args.size}, {args.threads} threads, medians of {args.reps}")
    for name, ms in rows:
        print(f"{name:28s} {ms:9.1f} ms  {ms / base:6.3f}x OIDN high")


if __name__ == "__main__":
    main()
