"""The detailed world's texture kinds side by side (docs/DATASETS.md).

    python scripts/detail_sheet.py OUT.jpg|OUT.png [--seeds 4] [--size 128]

One column per kind of :data:`mcdenoise.render.procedural.detail.DETAIL_KINDS`, one row per seed;
reflectances shown with gamma 1/2.2.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> None:
    from PIL import Image

    from mcdenoise.render.procedural.detail import DETAIL_KINDS, detail_texture

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--size", type=int, default=128)
    a = p.parse_args()
    rows = [np.concatenate([detail_texture(np.random.default_rng(s), k, a.size)[0] for k in DETAIL_KINDS], 1)
            for s in range(a.seeds)]
    img = (np.clip(np.concatenate(rows, 0), 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    Image.fromarray(img).save(a.out, quality=88)
    print(f"{a.out}: {len(DETAIL_KINDS)} kinds x {a.seeds} seeds ({', '.join(DETAIL_KINDS)})")


if __name__ == "__main__":
    main()
