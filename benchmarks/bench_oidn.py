"""The OIDN 2.5.1 baseline (`mcdenoise.eval.oidn`): where its figures come from.

    .venv/bin/python benchmarks/bench_oidn.py quality      # high/balanced/fast at 1920x1080: time, relMSE
    .venv/bin/python benchmarks/bench_oidn.py tolerance    # run-to-run noise behind tests/test_oidn.py
    .venv/bin/python benchmarks/bench_oidn.py parts        # each guide prefilter and colour mode at 1920x1080

``quality`` denoises a synthetic 1920x1080 HDR image (smooth colour times exponential noise, both
guides) with each quality, interleaved, the first round a warm-up; it prints the best time of each,
its relMSE (eps 1e-2) against the clean image, and the time ratios (the figures in
``oidn_denoise``'s docstring).

``tolerance`` measures, on the 48x40 test image of ``tests/test_oidn.py``, the largest change of
the output (relative to its maximum) over 20 repeated runs, after a random walk of 1-16 ulp on
every input, and from 1 to 16 threads (pyoidn's low-level API), against the change that reading
the wrong pixels makes: the gap ``RUN_TO_RUN_RTOL`` sits in.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from mcdenoise.eval.oidn import QUALITIES, oidn_denoise, version


def quality(reps: int) -> None:
    """Time and relMSE of each quality at 1920x1080 with albedo and normal guides."""
    rng = np.random.default_rng(0)
    h, w = 1080, 1920
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    clean = np.stack([2 + np.sin(xx / 40), 1 + np.cos(yy / 30), 0.5 + (xx + yy) / (h + w)]).astype(np.float32)
    color = (clean * rng.exponential(1.0, clean.shape)).astype(np.float32)
    albedo = np.clip(clean / 3, 0, 1).astype(np.float32)
    normal = np.zeros_like(clean)
    normal[2] = 1.0
    print("OIDN", version(), "cores", os.cpu_count(), "loadavg", os.getloadavg())
    times: dict[str, list[float]] = {q: [] for q in QUALITIES}
    outs: dict[str, np.ndarray] = {}
    for rep in range(reps + 1):  # round 0 is the warm-up (filter built for this size)
        for q in QUALITIES:
            t0 = time.perf_counter()
            outs[q] = oidn_denoise(color, albedo, normal, quality=q)
            if rep:
                times[q].append(time.perf_counter() - t0)
    for q, ts in times.items():
        err = float(np.mean((outs[q] - clean) ** 2 / (clean ** 2 + 1e-2)))
        print(f"{q:<9} best {min(ts):6.2f} s  runs {[round(t, 2) for t in ts]}  relMSE vs clean {err:.5f}")
    best = {q: min(ts) for q, ts in times.items()}
    print(f"high/fast = {best['high'] / best['fast']:.2f}x, high/balanced = {best['high'] / best['balanced']:.2f}x")
    print("loadavg after", os.getloadavg())


def parts(reps: int) -> None:
    """Time of each piece a combiner could spend OIDN on, at 1920x1080, relative to ``high``.

    The pieces: a guide prefilter (albedo or normal alone, each quality), the colour filter with
    noisy guides (each quality, albedo only or both) and with ``cleanAux`` guides. Interleaved,
    round 0 a warm-up; medians.
    """
    from mcdenoise.eval.oidn import oidn_prefilter

    rng = np.random.default_rng(0)
    h, w = 1080, 1920
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    clean = np.stack([2 + np.sin(xx / 40), 1 + np.cos(yy / 30), 0.5 + (xx + yy) / (h + w)]).astype(np.float32)
    color = (clean * rng.exponential(1.0, clean.shape)).astype(np.float32)
    albedo = np.clip(clean / 3 * rng.uniform(0.8, 1.2, clean.shape), 0, 1).astype(np.float32)
    normal = np.zeros_like(clean)
    normal[2] = 1.0
    pieces = {
        "colour high, albedo+normal": lambda: oidn_denoise(color, albedo, normal, quality="high"),
        "colour high, albedo only": lambda: oidn_denoise(color, albedo, None, quality="high"),
        "colour high, no guides": lambda: oidn_denoise(color, None, None, quality="high"),
        "colour balanced, albedo+normal": lambda: oidn_denoise(color, albedo, normal, quality="balanced"),
        "colour fast, albedo+normal": lambda: oidn_denoise(color, albedo, normal, quality="fast"),
        "colour high, cleanAux albedo+normal": lambda: oidn_denoise(color, albedo, normal, quality="high", clean_aux=True),
        "colour high, cleanAux albedo only": lambda: oidn_denoise(color, albedo, None, quality="high", clean_aux=True),
        "colour balanced, cleanAux albedo+normal": lambda: oidn_denoise(color, albedo, normal, quality="balanced", clean_aux=True),
    }
    for q in QUALITIES:
        pieces[f"albedo prefilter {q}"] = (lambda q=q: oidn_prefilter(albedo, "albedo", quality=q))
        pieces[f"normal prefilter {q}"] = (lambda q=q: oidn_prefilter(normal, "normal", quality=q))
    print("OIDN", version(), "cores", os.cpu_count(), "threads: OIDN's default", "loadavg", os.getloadavg())
    times: dict[str, list[float]] = {k: [] for k in pieces}
    for rep in range(reps + 1):
        for k, fn in pieces.items():
            t0 = time.perf_counter()
            fn()
            if rep:
                times[k].append(time.perf_counter() - t0)
    ref = float(np.median(times["colour high, albedo+normal"]))
    for k, ts in times.items():
        med = float(np.median(ts))
        print(f"{k:<42} median {med:6.2f} s  {med / ref:5.2f}x high")
    print("loadavg after", os.getloadavg())


def _lowlevel(img_hwc: np.ndarray, threads: int) -> np.ndarray:
    """OIDN ``high`` on (H, W, 3) with a set thread count (the wrapper leaves it to OIDN)."""
    import pyoidn

    out = np.empty_like(img_hwc)
    with pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU) as d:
        d.set_int("numThreads", threads)
        d.commit()
        f = pyoidn.Filter(d, pyoidn.OIDN_FILTER_TYPE_RT)
        try:
            f.set_image("color", img_hwc, pyoidn.OIDN_FORMAT_FLOAT3)
            f.set_image("output", out, pyoidn.OIDN_FORMAT_FLOAT3)
            f.set_bool("hdr", True)
            f.set_quality(pyoidn.OIDN_QUALITY_HIGH)
            f.commit()
            f.execute()
            assert d.get_error() is None, d.get_error()
        finally:
            f.release()
    return out


def tolerance() -> None:
    """Run-to-run, ulp and thread-count changes against the wrong-pixels change (48x40 image)."""
    rng = np.random.default_rng(1)
    clean = np.full((3, 48, 40), 5.0, np.float32)
    clean[:, :, 20:] *= 0.2
    noisy = clean * rng.exponential(1.0, clean.shape).astype(np.float32)
    wide = np.concatenate([noisy, noisy[:, :, ::-1] * 3], axis=2)
    view = wide[:, :, :40]
    for q in QUALITIES:
        want = oidn_denoise(np.ascontiguousarray(view), quality=q)
        m = float(np.abs(want).max())
        rep = max(float(np.abs(oidn_denoise(view, quality=q) - want).max()) for _ in range(20)) / m
        walk = np.random.default_rng(0)
        ulp = 0.0
        for _ in range(10):
            k = walk.integers(1, 17, view.shape).astype(np.int32)
            pert = (np.ascontiguousarray(view).view(np.int32) + k).view(np.float32)
            ulp = max(ulp, float(np.abs(oidn_denoise(pert, quality=q) - want).max()) / m)
        wrong = float(np.abs(oidn_denoise(np.ascontiguousarray(wide[:, :, 40:]), quality=q) - want).max()) / m
        print(f"{q}: repeat {rep:.2e}  ulp1-16 {ulp:.2e}  wrong-pixels {wrong:.2f}  (of max {m:.2f})")
    hwc = np.ascontiguousarray(np.moveaxis(view, 0, -1))
    base = _lowlevel(hwc, 1)
    spread = max(float(np.abs(_lowlevel(hwc, t) - base).max()) for t in (1, 2, 3, 4, 8, 16))
    print("threads 1..16 vs 1:", spread / float(np.abs(base).max()))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["quality", "tolerance", "parts"])
    p.add_argument("--reps", type=int, default=4, help="timed rounds after the warm-up (quality, parts)")
    args = p.parse_args()
    if args.what == "quality":
        quality(args.reps)
    elif args.what == "parts":
        parts(args.reps)
    else:
        tolerance()


if __name__ == "__main__":
    main()
