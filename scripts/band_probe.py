"""Would a second-stage candidate that swaps in the noisy mean's coarse band beat its base? (campaign 32, step 3)

Reads reports written with ``mcdenoise eval ... --save-images`` (``OUT/images/IMAGE/Kspp/METHOD.exr`` and
``reference.exr``). For each image, the candidate :func:`mcdenoise.models.refine.noisy_band` of the base
output and the noisy mean is formed for every box factor f and clamp c, and scored with the eval's own
relMSE and PSNR (docs/METRICS.md) against the reference, beside the base itself. Prints, per report and
over all reports: the mean relMSE and PSNR of the base and of each (f, c), and on how many images each
candidate is better than the base in relMSE. No learning: a candidate that loses to its base everywhere
gives a second stage nothing to pick.

    python scripts/band_probe.py reports/c32_train_detail reports/c32_train_plain --base layer-medium --spp 4
    python scripts/band_probe.py ... --f 8 16 --c 2 4 8 --exclude 2 4     (bright pixels left out of the box)
"""
from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np
import torch

from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.io.exr import read_exr
from mcdenoise.models.refine import noisy_band


def score(report: Path, base_name: str, spp: int, fs: list[int], cs: list[float],
          ts: list[float | None] | None = None) -> dict[str, list[tuple[float, float]]]:
    """method label -> [(relMSE, PSNR) per image] for ``base`` and every ``f<F> c<C>`` candidate
    (``f<F> c<C> T<T>`` with bright pixels left out of the box, for each ``T`` of ``ts``; None: none left out)."""
    out: dict[str, list[tuple[float, float]]] = {}
    refs = sorted((report / "images").rglob("reference.exr"))
    if not refs:
        raise SystemExit(f"{report}: no saved images (run eval with --save-images)")
    for ref_path in refs:
        d = ref_path.parent / f"{spp}spp"
        if not (d / f"{base_name}.exr").is_file() or not (d / "noisy.exr").is_file():
            continue
        ref = torch.from_numpy(read_exr(ref_path)["radiance"].astype(np.float64))[None]
        base = torch.from_numpy(read_exr(d / f"{base_name}.exr")["radiance"].astype(np.float64))[None]
        noisy = torch.from_numpy(read_exr(d / "noisy.exr")["radiance"].astype(np.float64))[None]
        imgs = {"base": base}
        for f, c, t in itertools.product(fs, cs, ts or [None]):
            label = f"f{f} c{c:g}" + ("" if t is None else f" T{t:g}")
            imgs[label] = noisy_band(base, noisy, f, c, exclude=t)
        for label, x in imgs.items():
            out.setdefault(label, []).append((float(relmse(x, ref)), float(psnr(x, ref))))
    if not out:
        raise SystemExit(f"{report}: no image has {base_name}.exr and noisy.exr at {spp} spp")
    return out


def table(name: str, res: dict[str, list[tuple[float, float]]]) -> list[str]:
    b = np.array(res["base"])
    lines = [f"{name} ({len(b)} images): method | mean relMSE | mean PSNR | images with lower relMSE than the base"]
    for label, rows in res.items():
        r = np.array(rows)
        better = "" if label == "base" else f" | {int((r[:, 0] < b[:, 0]).sum())}/{len(r)}"
        lines.append(f"  {label:13s} | {r[:, 0].mean():.5f} | {r[:, 1].mean():.4f}{better}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("reports", type=Path, nargs="+")
    ap.add_argument("--base", default="layer-medium", help="the method whose output is the base")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--f", type=int, nargs="+", default=[8, 16], help="box factors (a (2f-1)^2 box)")
    ap.add_argument("--c", type=float, nargs="+", default=[2, 4, 8, 16], help="clamps, times the base's 3x3 maximum")
    ap.add_argument("--exclude", type=float, nargs="+", default=None, metavar="T",
                    help="leave pixels brighter than T times their box mean out of the box (noisy_band's exclude)")
    a = ap.parse_args()
    pooled: dict[str, list[tuple[float, float]]] = {}
    for rep in a.reports:
        res = score(rep, a.base, a.spp, a.f, a.c, a.exclude)
        print("\n".join(table(str(rep), res)))
        for k, v in res.items():
            pooled.setdefault(k, []).extend(v)
    if len(a.reports) > 1:
        print("\n".join(table("all reports", pooled)))


if __name__ == "__main__":
    main()
