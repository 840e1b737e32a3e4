"""Measure the data format on a synthetic image: write time, full read, random-crop reads.

Run: ``.venv/bin/python benchmarks/bench_io.py --size 256 --spp 16 --crop 64``. Prints one JSON object;
nothing is kept on disk (a temporary folder is used).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mcdenoise.data.format import ImageMeta, read_image, write_image  # noqa: E402

CHANNELS = ("radiance", "albedo", "normal", "depth")


def run(size: int, spp: int, crop: int, crops: int, seed: int = 0) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    samples = {
        "radiance": (rng.random((spp, 3, size, size), dtype=np.float32) * 4),
        "albedo": rng.random((spp, 3, size, size), dtype=np.float32),
        "normal": rng.random((spp, 3, size, size), dtype=np.float32) * 2 - 1,
        "depth": rng.random((spp, 1, size, size), dtype=np.float32) * 10,
    }
    raw_bytes = sum(a.nbytes for a in samples.values())
    meta = ImageMeta(width=size, height=size, spp=spp, channels=list(CHANNELS), scene="bench")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        folder = write_image(Path(tmp) / "img", meta=meta, samples=samples)
        t_write = time.perf_counter() - t0
        im = read_image(folder)
        file_bytes = (folder / "samples.bin").stat().st_size
        t0 = time.perf_counter()
        im.samples.read()
        t_full = time.perf_counter() - t0
        im.samples.bytes_read = 0
        t0 = time.perf_counter()
        for _ in range(crops):
            y0, x0 = (int(v) for v in rng.integers(0, size - crop + 1, 2))
            im.samples.read(crop=(y0, x0, crop, crop), samples=sorted(rng.choice(spp, 4, replace=False)))
        t_crop = (time.perf_counter() - t0) / crops
        crop_bytes = im.samples.bytes_read / crops
        t0 = time.perf_counter()
        im.read_noisy()
        t_noisy = time.perf_counter() - t0
    return {
        "size": size, "spp": spp, "crop": crop,
        "raw_float32_MB": raw_bytes / 2**20,
        "samples_bin_MB": file_bytes / 2**20,
        "write_image_s": t_write,
        "full_read_s": t_full,
        "crop_4spp_read_ms": t_crop * 1e3,
        "crop_4spp_bytes_fraction_of_file": crop_bytes / file_bytes,
        "read_noisy_s": t_noisy,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--crops", type=int, default=50)
    args = ap.parse_args()
    print(json.dumps({k: round(v, 4) if isinstance(v, float) else v
                      for k, v in run(args.size, args.spp, args.crop, args.crops).items()}, indent=1))


if __name__ == "__main__":
    main()
