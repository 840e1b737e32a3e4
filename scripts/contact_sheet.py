"""Contact sheet of a procedural dataset's noisy images (docs/DATASETS.md).

    python scripts/contact_sheet.py DATASET OUT.jpg|OUT.png [--count 24] [--tile 128]

Tonemapped x / (1 + x), sRGB-ish gamma 1/2.2, one view per scene, downscaled by box filtering.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    from PIL import Image

    from mcdenoise.io.exr import read_exr

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--count", type=int, default=24)
    p.add_argument("--tile", type=int, default=128)
    p.add_argument("--cols", type=int, default=8)
    a = p.parse_args()
    paths = (sorted(a.dataset.glob("proc_*/view_000/noisy.exr")) or sorted(a.dataset.glob("proc_*/noisy.exr")))[: a.count]
    tiles = []
    for path in paths:
        x = np.asarray(read_exr(path)["radiance"], np.float32).transpose(1, 2, 0)
        f = max(1, x.shape[0] // a.tile)
        x = x[: x.shape[0] // f * f, : x.shape[1] // f * f].reshape(x.shape[0] // f, f, x.shape[1] // f, f, 3).mean((1, 3))
        tiles.append((np.clip(x / (1 + x), 0, 1) ** (1 / 2.2) * 255).astype(np.uint8))
    rows = (len(tiles) + a.cols - 1) // a.cols
    h, w = tiles[0].shape[:2]
    sheet = np.zeros((rows * h, a.cols * w, 3), np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, a.cols)
        sheet[r * h : (r + 1) * h, c * w : (c + 1) * w] = t
    Image.fromarray(sheet).save(a.out, quality=85) if a.out.suffix.lower() in (".jpg", ".jpeg") else Image.fromarray(sheet).save(a.out, optimize=True)
    print(f"{a.out}: {len(tiles)} images")


if __name__ == "__main__":
    main()
