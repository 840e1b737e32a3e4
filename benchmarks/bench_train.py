"""Training speed of every model's ``small`` preset: seconds per step and crops per second.

    .venv/bin/python benchmarks/bench_train.py --data DATASET_DIR            # all models, defaults of `mcdenoise train`
    .venv/bin/python benchmarks/bench_train.py --data D --models kpcn wskp --batch 8 --crop 48 --workers 2
    .venv/bin/python benchmarks/bench_train.py --quick                        # tiny synthetic data, checks the script runs
    .venv/bin/python benchmarks/bench_train.py --data D --json out.json       # also write the numbers

Three figures per model, each the median over ``--steps`` timed steps after ``--warmup`` untimed ones:

* ``compute s/step``: forward + backward + clipped Adam step on batches already in memory
  (what the model costs; the first ``warmup + steps`` batches of the run, so the same spp mix);
* ``data crops/s``: batches drawn by :func:`mcdenoise.train.data.training_batches` with
  ``--workers`` loader processes and nothing else (what reading, crop selection and augmentation
  can feed);
* ``train s/step`` and ``train crops/s``: both together, as ``mcdenoise train`` runs them.

Print a Markdown table (paste it into docs/TRAINING.md). On a 2-core machine the loader workers
and the training threads share the cores: try ``--workers 0 1 2`` and ``--threads 1 2``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _timing import median_time  # noqa: E402  (benchmarks/ is the script's folder)
from mcdenoise.models.info import count_parameters  # noqa: E402
from mcdenoise.models.registry import build_model, list_models  # noqa: E402
from mcdenoise.train.config import TrainConfig  # noqa: E402
from mcdenoise.train.data import batch_source, training_batches  # noqa: E402
from mcdenoise.train.trainer import Trainer, data_config  # noqa: E402


def bench_model(name: str, data: Path, args: argparse.Namespace, workers: int) -> dict[str, Any]:
    torch.manual_seed(0)
    model = build_model(name, args.preset)
    cfg = TrainConfig(model=name, data=str(data), steps=100_000, batch=args.batch, crop=args.crop, workers=workers,
                      sampling=args.sampling, amp=args.amp,
                      spp_range=tuple(args.spp) if args.spp else None).resolved(model.input_kind)
    dcfg = data_config(cfg)
    tr = Trainer(model, cfg, torch.device(args.device))
    # The same batches the data figure reads (sample models draw their spp per batch, and cost
    # grows with it), prepared up front so that only the model is timed.
    source = batch_source(data, model, dcfg)
    ready = iter([{k: v.to(args.device) for k, v in source[t].items()} for t in range(args.warmup + args.steps)])
    step_counter = iter(range(10**9))
    compute = median_time(lambda: tr.step(next(ready), next(step_counter)), args.steps, args.warmup)

    it = training_batches(data, model, dcfg, start_step=0, device=args.device)
    data_s = median_time(lambda: next(it), args.steps, args.warmup)
    del it

    it = training_batches(data, model, dcfg, start_step=10_000, device=args.device)
    train_s = median_time(lambda: tr.step(next(it), next(step_counter)), args.steps, args.warmup)
    del it
    return {
        "model": name,
        "params": count_parameters(model),
        "input": model.input_kind,
        "spp": list(cfg.spp_range) if cfg.spp_range else "stored",
        "workers": workers,
        "compute_s_per_step": compute,
        "data_crops_per_s": args.batch / data_s,
        "train_s_per_step": train_s,
        "train_crops_per_s": args.batch / train_s,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, help="dataset folder from `mcdenoise dataset` (required unless --quick)")
    ap.add_argument("--models", nargs="*", help="default: every registered model")
    ap.add_argument("--preset", default="small", help="preset of every model (default small)")
    ap.add_argument("--amp", default="none", choices=("none", "bf16"), help="as `mcdenoise train --amp`")
    ap.add_argument("--spp", type=int, nargs=2, default=None, metavar=("MIN", "MAX"),
                    help="sample models' spp range (default: train's)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=48)
    ap.add_argument("--workers", type=int, nargs="*", default=[2])
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    ap.add_argument("--sampling", default="importance", choices=("importance", "uniform"))
    ap.add_argument("--steps", type=int, default=10, help="timed steps per figure")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="tiny synthetic dataset, batch 2, crop 16, 2 steps")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    tmp = None
    if args.quick:
        sys.path.insert(0, str(ROOT / "tests"))
        from train_tiny_data import make_tiny_dataset

        tmp = tempfile.TemporaryDirectory(prefix="bench_train_")
        args.data = make_tiny_dataset(Path(tmp.name) / "data", spp=4, size=24)
        args.batch, args.crop, args.steps, args.warmup = 2, 16, 2, 1
    if args.data is None:
        ap.error("--data is required (or --quick)")
    names = args.models or [e.name for e in list_models()]
    rows = []
    for w in args.workers:
        for name in names:
            r = bench_model(name, args.data, args, w)
            rows.append(r)
            print(f"  {name}: {r['train_s_per_step']:.3f} s/step", file=sys.stderr, flush=True)
    head = (f"preset {args.preset}, amp {args.amp}, batch {args.batch}, crop {args.crop}, {args.sampling} crops, device {args.device}, "
            f"{torch.get_num_threads()} torch threads, {os.cpu_count()} cores ({platform.processor() or platform.machine()})")
    print(f"\n{head}\n")
    print("| model | params | input spp | workers | compute s/step | data crops/s | train s/step | train crops/s |")
    print("|---|---:|---|---:|---:|---:|---:|---:|")
    for r in rows:
        spp = "stored" if r["spp"] == "stored" else f"{r['spp'][0]}-{r['spp'][1]}"
        print(f"| {r['model']} | {r['params']:,} | {spp} | {r['workers']} | {r['compute_s_per_step']:.3f} | "
              f"{r['data_crops_per_s']:.1f} | {r['train_s_per_step']:.3f} | {r['train_crops_per_s']:.1f} |")
    if args.json:
        args.json.write_text(json.dumps({"settings": head, "rows": rows}, indent=1) + "\n")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
