"""How spiky was a run's training loss? Median, 95th percentile and maximum of the per-step training
loss in each run's metrics.csv (every step: validation figures share their step's row), for losses
whose rare huge pixels the gradient clip has to absorb (docs/TRAINING.md, "Losses": `relmse_in_wide`).

    python scripts/loss_spread.py campaigns/c19/layer_m19w campaigns/c18/layer_m18s4 campaigns/c19/layer_m19m
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mcdenoise.train.runlog import read_metrics


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path, help="run folders with a metrics.csv")
    a = ap.parse_args()
    for run in a.runs:
        rows = read_metrics(run / "metrics.csv")
        loss = np.array([float(r["loss"]) for r in rows if r["loss"]])
        if loss.size == 0:
            raise SystemExit(f"{run / 'metrics.csv'}: no training rows")
        print(f"{str(run):40s} {loss.size:5d} steps: median {np.median(loss):.3f}, "
              f"95th percentile {np.percentile(loss, 95):.2f}, max {loss.max():.1f}")


if __name__ == "__main__":
    main()
