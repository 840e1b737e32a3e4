"""Where one training step's time goes: ``torch.profiler`` over a single ``Trainer.step`` (forward,
backward, clipped Adam) on a real batch, after one untimed step.

    .venv/bin/python benchmarks/profile_train_step.py --data data/detail_ref --model layer --preset medium --amp bf16

Prints the operators with the most self CPU time, and the share of the step spent in dtype/layout
copies (``aten::copy_``) and in ``aten::addcmul_`` (the per-tap loops of the kernel filters), the
two figures docs/TRAINING.md ("bfloat16 on the CPU") quotes.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mcdenoise.models.registry import build_model  # noqa: E402
from mcdenoise.train.config import TrainConfig  # noqa: E402
from mcdenoise.train.data import batch_source  # noqa: E402
from mcdenoise.train.trainer import Trainer, data_config  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="dataset folder from `mcdenoise dataset`")
    ap.add_argument("--model", default="layer")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--amp", default="bf16", choices=("none", "bf16"))
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=96)
    ap.add_argument("--spp", type=int, default=8, help="input spp of the batch (sample models)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rows", type=int, default=20, help="operators listed")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    model = build_model(a.model, a.preset)
    cfg = TrainConfig(model=a.model, data=str(a.data), steps=100_000, batch=a.batch, crop=a.crop, workers=0,
                      amp=a.amp, spp_range=(a.spp, a.spp)).resolved(model.input_kind)
    batch = batch_source(a.data, model, data_config(cfg))[0]
    tr = Trainer(model, cfg, torch.device("cpu"))
    tr.step(batch, 0)  # first-call allocations and oneDNN primitive creation are not the step's cost
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        tr.step(batch, 1)
    events = prof.key_averages()
    print(events.table(sort_by="self_cpu_time_total", row_limit=a.rows))
    total = sum(e.self_cpu_time_total for e in events)
    for op in ("aten::copy_", "aten::addcmul_"):
        share = sum(e.self_cpu_time_total for e in events if e.key == op) / total
        print(f"{op}: {100 * share:.0f}% of the step's self CPU time")
    print(f"({a.model} {a.preset}, amp {a.amp}, batch {a.batch}, crop {a.crop}, {a.spp} spp, {a.threads} threads)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
