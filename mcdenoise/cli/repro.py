"""Reproduce paper experiments: ``mcdenoise repro splat-vs-gather [--steps N] [--seed S] [--out DIR]``."""

from __future__ import annotations

import argparse
import json
import sys

from mcdenoise.repro import EXPERIMENTS


def add_parser(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="experiment", metavar="EXPERIMENT")
    sv = sub.add_parser("splat-vs-gather", help=EXPERIMENTS["splat-vs-gather"],
                        description=EXPERIMENTS["splat-vs-gather"])
    sv.add_argument("--steps", type=int, default=400, help="Adam steps per network (default 400)")
    sv.add_argument("--seed", type=int, default=0, help="seed of data and initialisation (default 0)")
    sv.add_argument("--batch", type=int, default=8, help="textures per step (default 8)")
    sv.add_argument("--out", default="runs/repro", help="folder for splat_vs_gather.json (default runs/repro)")
    sv.add_argument("--json", action="store_true", help="print the summary as JSON")
    sv.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:
    if args.experiment is None:
        print("mcdenoise repro: choose an experiment: " + ", ".join(EXPERIMENTS), file=sys.stderr)
        return 2
    if args.experiment == "splat-vs-gather":
        from mcdenoise.repro.splat_vs_gather import ToyConfig, run_experiment, write_result

        if args.steps < 1 or args.batch < 1:
            print("mcdenoise repro: --steps and --batch must be >= 1", file=sys.stderr)
            return 2
        cfg = ToyConfig(steps=args.steps, seed=args.seed, batch=args.batch)
        log = (lambda s: None) if args.quiet or args.json else (lambda s: print(s, flush=True))
        res = run_experiment(cfg, log=log)
        path = write_result(res, args.out)
        summary = {k: res[k] for k in ("parameters", "final_train_loss", "test_loss", "test_loss_fixed_gaussian",
                                       "train_seconds")}
        summary["json"] = str(path)
        if args.json:
            print(json.dumps(summary, indent=1))
            return 0
        p, tr, te = res["parameters"], res["final_train_loss"], res["test_loss"]
        print(f"parameters: gather {p['gather']}, splat {p['splat']}")
        print(f"final training loss (mean of last 10% of steps): gather {tr['gather']:.5f}, splat {tr['splat']:.5f}")
        print(f"held-out test loss: gather {te['gather']:.5f}, splat {te['splat']:.5f} "
              f"(fixed Gaussian, no outlier handling: {res['test_loss_fixed_gaussian']:.5f})")
        better = "splat" if te["splat"] < te["gather"] else "gather"
        ratio = max(te.values()) / max(min(te.values()), 1e-30)
        print(f"{better} has the lower test loss, by a factor {ratio:.2f}; curves in {path}")
        return 0
    print(f"mcdenoise repro: unknown experiment {args.experiment!r}", file=sys.stderr)
    return 2
