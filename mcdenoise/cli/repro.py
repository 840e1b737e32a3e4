"""Reproduce paper experiments: ``mcdenoise repro EXPERIMENT [options]``.

``splat-vs-gather`` is the SBMC Fig. 4 toy; the others train variants of our models with the
training engine on a procedural dataset (rendered once into ``--out``/data) or on ``--data``.
"""

from __future__ import annotations

import argparse
import json
import sys

from mcdenoise.repro import EXPERIMENTS, TRAINED

RESULTS_HEADING = "## Reproductions of the papers' claims"


def _positive(s: str) -> int:
    v = int(s)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


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
    for name in TRAINED:
        ep = sub.add_parser(name, help=EXPERIMENTS[name], description=EXPERIMENTS[name]
                            + ". Trains every variant at the same steps, batch, crops and data; reruns skip finished runs.")
        ep.add_argument("--data", default=None,
                        help="dataset folder with train and val splits (default: render a small procedural one "
                             "into OUT/data once, shared by all experiments)")
        ep.add_argument("--steps", type=_positive, default=None, help="steps per variant (default: the experiment's, "
                        "about 10 minutes in all on 2 CPU cores)")
        ep.add_argument("--seed", type=int, default=0, help="seed of weights and batches (default 0)")
        ep.add_argument("--out", default="runs/repro", help="folder for data, runs and results (default runs/repro)")
        ep.add_argument("--write-docs", metavar="PATH", default=None,
                        help=f"write the result as block repro:{name} into this Markdown file (e.g. docs/RESULTS.md)")
        ep.add_argument("--json", action="store_true", help="print the result as JSON")
        ep.add_argument("--quiet", action="store_true", help="no progress lines")


def _run_toy(args: argparse.Namespace) -> int:
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


def _run_trained(args: argparse.Namespace) -> int:
    from mcdenoise.repro import load_experiment
    from mcdenoise.repro.common import METRIC_NAMES, run_experiment

    exp = load_experiment(args.experiment)
    quiet = args.quiet or args.json
    log = (lambda s: None) if quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    res = run_experiment(exp, data=args.data, steps=args.steps, seed=args.seed, out=args.out, log=log,
                         progress=not quiet and sys.stderr.isatty())
    if args.write_docs:
        from mcdenoise.eval.docblock import replace_block
        from mcdenoise.repro.report import markdown_block

        replace_block(args.write_docs, f"repro:{exp.name}", markdown_block(res, exp.notes), heading=RESULTS_HEADING)
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    m = res["metric"]
    print(f"{res['title']}: {res['steps']} steps per variant, seed {res['seed']}")
    for v in res["variants"].values():
        print(f"  {v['label']:<28} {v['parameters']:>9,} params  final val {METRIC_NAMES[m]} {v['final'][m]:.5g}  "
              f"({v['wall_s']:.0f} s)")
    print(f"verdict: {res['verdict']}. {res['explanation']}")
    print(f"result: {res['json']}; plot: {res['plot']}" + (f"; block repro:{exp.name} in {args.write_docs}"
                                                          if args.write_docs else ""))
    return 0


def run(args: argparse.Namespace) -> int:
    if args.experiment is None:
        print("mcdenoise repro: choose an experiment: " + ", ".join(EXPERIMENTS), file=sys.stderr)
        return 2
    if args.experiment == "splat-vs-gather":
        return _run_toy(args)
    if args.experiment in TRAINED:
        return _run_trained(args)
    print(f"mcdenoise repro: unknown experiment {args.experiment!r}", file=sys.stderr)
    return 2
