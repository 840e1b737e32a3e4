"""Training-data throughput: crops/s that ``training_batches`` delivers, without any model work.

    python benchmarks/bench_train_data.py DATASET_DIR [--models kpcn sbmc] [--workers 0 2]
        [--batches 40] [--crop 48] [--batch 8] [--sampling importance]

Prints one line per (model, workers): crops/s after the first (warm-up) batches, i.e. the rate a
training loop that takes no time would see, and for ``workers=0`` also crops per CPU second of
the reading process (what one core delivers; stable on a loaded machine, where wall-clock rates
are not). The model only decides which channels are read.
"""

from __future__ import annotations

import argparse
import time

from mcdenoise.models.registry import build_model
from mcdenoise.train.data import DataConfig, training_batches


def measure(data: str, model_name: str, workers: int, batches: int, **cfg_kw: object) -> tuple[float, float]:
    """``(crops per wall second, crops per CPU second of this process)`` over ``batches`` batches
    after ``2 * max(workers, 1)`` warm-up batches."""
    model = build_model(model_name, "small")
    cfg = DataConfig(workers=workers, **cfg_kw)  # type: ignore[arg-type]
    it = training_batches(data, model, cfg)
    for _ in range(2 * max(workers, 1)):  # worker start-up and first EXR decodes
        next(it)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(batches):
        next(it)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    it.close()
    n = batches * cfg.batch
    return n / dt, n / max(dc, 1e-9)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data")
    p.add_argument("--models", nargs="+", default=["kpcn", "sbmc"])
    p.add_argument("--workers", nargs="+", type=int, default=[0, 2])
    p.add_argument("--batches", type=int, default=40)
    p.add_argument("--crop", type=int, default=48)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--sampling", default="importance", choices=["importance", "uniform"])
    a = p.parse_args()
    for m in a.models:
        for w in a.workers:
            rate, per_cpu = measure(a.data, m, w, a.batches, crop=a.crop, batch=a.batch, sampling=a.sampling)
            cpu = f"  {per_cpu:8.1f} crops/CPU-s" if w == 0 else ""
            print(f"{m:12s} workers={w}  crop={a.crop} batch={a.batch} {a.sampling:10s} {rate:8.1f} crops/s{cpu}", flush=True)


if __name__ == "__main__":
    main()
