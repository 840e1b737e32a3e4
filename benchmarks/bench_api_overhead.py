"""What ``mcdenoise.denoise`` adds over the bare model call, with the same shipped weights on both sides.

Pairs of calls (bare forward on tensors in place, then the API on numpy arrays; the order
alternates per pair) on random 1920x1080 colour, albedo, normal and depth; prints both medians and
their ratio. ``--no-cache`` turns off the prepared-model cache of ``mcdenoise.infer.choose`` (each
API call then loads and folds the weights again, as before issue 18's fix).

    python benchmarks/bench_api_overhead.py --model wskp --pairs 9 [--no-cache]
"""
from __future__ import annotations

import argparse
import time

import _timing  # noqa: F401 -- puts the repository on sys.path
import numpy as np
import torch

import mcdenoise
import mcdenoise.infer.choose as choose
from mcdenoise.models.inference import inference_context, prepare_inference, resolve_precision
from mcdenoise.models.weights import load_denoiser, shipped_weights


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="wskp", help="a shipped pixel model (colour, albedo, normal, depth)")
    ap.add_argument("--size", default="1920x1080")
    ap.add_argument("--pairs", type=int, default=9)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-cache", action="store_true")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    if a.no_cache:
        choose._PREPARED_MAX = 0
    w, h = (int(v) for v in a.size.split("x"))
    rng = np.random.default_rng(0)
    c, al = rng.random((3, h, w), dtype=np.float32), rng.random((3, h, w), dtype=np.float32)
    n, d = rng.random((3, h, w), dtype=np.float32) * 2 - 1, rng.random((1, h, w), dtype=np.float32)
    weights = str(shipped_weights(a.model).weights)
    precision = resolve_precision("auto", "cpu")
    model = prepare_inference(load_denoiser(weights)[0], fast=True, precision=precision)
    batch = {k: torch.from_numpy(v)[None] for k, v in (("radiance", c), ("albedo", al), ("normal", n), ("depth", d))}

    def bare() -> None:
        with inference_context(True):
            model(batch)

    def api() -> None:
        mcdenoise.denoise(c, albedo=al, normal=n, depth=d, model=weights, precision=precision)

    for f in (bare, api, bare, api):  # warm-up
        f()
    times: dict[str, list[float]] = {"bare": [], "api": []}
    for i in range(a.pairs):
        order = ((bare, "bare"), (api, "api")) if i % 2 == 0 else ((api, "api"), (bare, "bare"))
        for f, name in order:
            t0 = time.perf_counter()
            f()
            times[name].append(time.perf_counter() - t0)
    mb, ma = np.median(times["bare"]), np.median(times["api"])
    print(f"{a.model} {a.size}, {precision} trunks, {a.threads} threads, {a.pairs} pairs"
          f"{', no model cache' if a.no_cache else ''}: bare {mb * 1e3:.1f} ms, API {ma * 1e3:.1f} ms, API/bare {ma / mb:.3f}")


if __name__ == "__main__":
    main()
