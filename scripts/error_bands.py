"""At what scale one denoiser's error exceeds another's: relMSE of k x k block means.

Reads a report written with ``mcdenoise eval ... --save-images`` (``OUT/images/.../IMAGE/Kspp/METHOD.exr``
and ``OUT/images/IMAGE/reference.exr``). For each block size k, both the output and the reference
are averaged over k x k blocks (the image cropped to a multiple of k) and scored with relMSE
(``mean((x - y)^2 / (y^2 + 0.01))``, per channel, as docs/METRICS.md). k = 1 is the plain relMSE; a
large k keeps only the error that does not average out inside a block: low-frequency blotches, a
wrong overall level. Prints, per spp and k, each method's mean over the images, the ratio of the
means A / B, the geometric mean of the per-image ratios, and the same for the images whose name
contains ``--focus`` (e.g. one scene).

    python scripts/error_bands.py reports/c28_bands layer-medium oidn-high [--focus bathroom]
"""
from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

from mcdenoise.io.exr import read_exr

EPS = 1e-2


def block_mean(img: np.ndarray, k: int) -> np.ndarray:
    """(C, H, W) -> (C, H // k, W // k): means of k x k blocks (the remainder rows/columns dropped)."""
    c, h, w = img.shape
    h2, w2 = h // k, w // k
    return img[:, :h2 * k, :w2 * k].reshape(c, h2, k, w2, k).mean(axis=(2, 4))


def band_relmse(x: np.ndarray, y: np.ndarray, k: int) -> float:
    xb, yb = block_mean(x.astype(np.float64), k), block_mean(y.astype(np.float64), k)
    return float(np.mean((xb - yb) ** 2 / (yb ** 2 + EPS)))


def collect(report: Path, methods: list[str], ks: list[int]) -> dict[int, dict[str, dict[str, list[float]]]]:
    """spp -> image -> method -> [relMSE at each k]. An image is named by its folder's path under
    ``images/`` (``detail_ref/proc_000031/view_000``): a dataset's views, or two datasets' scenes, share
    folder names, so the last folder's name alone merged 46 held-out images into 10."""
    out: dict[int, dict[str, dict[str, list[float]]]] = collections.defaultdict(dict)
    for ref_path in sorted((report / "images").rglob("reference.exr")):
        folder = ref_path.parent
        name = folder.relative_to(report / "images").as_posix()
        ref = read_exr(ref_path)["radiance"]
        for kdir in sorted(folder.glob("*spp")):
            spp = int(kdir.name[:-3])
            row = {}
            for m in methods:
                p = kdir / f"{m}.exr"
                if p.is_file():
                    x = read_exr(p)["radiance"]
                    row[m] = [band_relmse(x, ref, k) for k in ks]
            if len(row) == len(methods):
                out[spp][name] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path)
    ap.add_argument("a", help="method A (e.g. layer-medium)")
    ap.add_argument("b", help="method B, the baseline (e.g. oidn-high)")
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    ap.add_argument("--focus", default=None, help="also report the images whose name contains this")
    a = ap.parse_args()
    data = collect(a.report, [a.a, a.b], a.ks)
    if not data:
        raise SystemExit(f"{a.report}: no saved images of {a.a} and {a.b} (run eval with --save-images)")
    for spp in sorted(data):
        groups = {"all": data[spp]}
        if a.focus:
            groups[a.focus] = {im: v for im, v in data[spp].items() if a.focus in im}
        for gname, imgs in groups.items():
            if not imgs:
                continue
            print(f"{spp} spp, {gname} ({len(imgs)} images): k | {a.a} | {a.b} | ratio of means | geo-mean ratio")
            for i, k in enumerate(a.ks):
                va = np.array([v[a.a][i] for v in imgs.values()])
                vb = np.array([v[a.b][i] for v in imgs.values()])
                geo = float(np.exp(np.mean(np.log(va / vb))))
                print(f"  {k:3d} | {va.mean():.5f} | {vb.mean():.5f} | {va.mean() / vb.mean():.3f} | {geo:.3f}")


if __name__ == "__main__":
    main()
