"""Time of a self-ensemble (8 orientations, per-pixel median) against one pass, through
``denoise_inputs`` as ``mcdenoise denoise --self-ensemble`` runs it (campaign 20).

    .venv/bin/python benchmarks/bench_self_ensemble.py --models layer-medium layer --size 256 --spp 4 --threads 2

Synthetic per-sample input (``synthetic_batch``) of ``size x size`` pixels; shipped weights by name,
float32. Prints, per model, the median of ``--repeats`` timed calls of each mode (interleaved, after
one warm-up) and their ratio, measured in the same run; the CPU model, torch threads and precision are printed too.
"""
from __future__ import annotations

import argparse
import statistics

import _timing  # noqa: F401  (puts the repository on sys.path)
import torch

from mcdenoise.bench.machine import machine_info
from mcdenoise.bench.timing import median_time
from mcdenoise.infer.run import denoise_inputs
from mcdenoise.infer.sources import from_arrays
from mcdenoise.models import synthetic_batch
from mcdenoise.models.weights import load_denoiser


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=["layer-medium"])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    info = machine_info("cpu")
    print(f"CPU {info['cpu']}; load average {info.get('load_start')}; torch {a.threads} thread(s); float32; {a.size}x{a.size}, {a.spp} spp; "
          f"median of {a.repeats} interleaved calls after 1 warm-up")
    for spec in a.models:
        model, _ = load_denoiser(spec)
        model.eval()
        batch = synthetic_batch(model, spp=a.spp, height=a.size, width=a.size, generator=torch.Generator().manual_seed(0))
        if model.input_kind == "samples":
            samples = {k: v[0].numpy() for k, v in batch.items() if k != "scene_features"}
            inputs = from_arrays(samples["radiance"].mean(0), samples=samples,
                                 scene_features=batch["scene_features"][0].numpy())
        else:
            pixels = {k: v[0].numpy() for k, v in batch.items()}
            inputs = from_arrays(pixels.pop("radiance"), features=pixels)
        runs = {se: (lambda se=se: denoise_inputs(inputs, model, device="cpu", progress=False, self_ensemble=se))
                for se in (False, True)}
        for fn in runs.values():
            fn()  # warm-up
        # interleaved, so that a change of load on the machine falls on both modes alike
        samples: dict[bool, list[float]] = {False: [], True: []}
        for _ in range(a.repeats):
            for se, fn in runs.items():
                samples[se].append(median_time(fn, 1))
        times = {se: statistics.median(ts) for se, ts in samples.items()}
        mp = a.size * a.size / 1e6
        print(f"{spec:14s} one pass {times[False] / mp:8.2f} s/MP   self-ensemble {times[True] / mp:8.2f} s/MP   "
              f"ratio {times[True] / times[False]:.2f}x")


if __name__ == "__main__":
    main()
