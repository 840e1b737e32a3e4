"""Scores of an evaluation: every metric of one output against its reference, the means per
(subset, method, spp), and results.csv."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.eval.images import EvalImage
from mcdenoise.eval.metrics import compute_metrics
from mcdenoise.io.atomic import atomic_file

__all__ = ["CSV_FIELDS", "SUBSETS", "image_metrics", "finite_or_none", "summarize", "write_csv"]

#: Leading columns of results.csv; one column per metric follows.
CSV_FIELDS = ("image", "spp", "method", "seconds", "ms_per_mpix")
#: Subsets summarised separately: name -> the image effects that put an image in it.
SUBSETS = {"all": None, "dof_motion": ("depth_of_field", "motion_blur")}


def finite_or_none(v: float | None) -> float | None:
    """JSON has no NaN/Inf: non-finite values (a diverged model) become null."""
    return v if v is not None and math.isfinite(v) else None


def image_metrics(y: np.ndarray, ref: np.ndarray, names: list[str]) -> dict[str, float | None]:
    """Every metric of ``names`` in float64; DSSIM is ``1 - SSIM`` (:func:`metrics.dssim`), so SSIM is
    computed once when both are asked for."""
    both = "ssim" in names and "dssim" in names
    vals = compute_metrics(y.astype(np.float64), ref.astype(np.float64), [n for n in names if not (both and n == "dssim")])
    if both:
        vals["dssim"] = 1.0 - vals["ssim"]
    return {n: finite_or_none(vals[n]) for n in names}


def summarize(rows: list[dict[str, Any]], images: list[EvalImage], methods: list[str], spps: list[int],
              metric_names: list[str]) -> list[dict[str, Any]]:
    """Means per (subset, method, spp): every metric over the subset's images, and ms per megapixel
    (total time over total megapixels). Subsets without images are left out."""
    effects = {im.id: set(im.effects) for im in images}
    mpix = {im.id: im.folder.meta.width * im.folder.meta.height / 1e6 for im in images}
    out = []
    for subset, need in SUBSETS.items():
        keep = [r for r in rows if need is None or effects[r["image"]] & set(need)]
        for m in methods:
            for k in spps:
                sel = [r for r in keep if r["method"] == m and r["spp"] == k]
                if not sel:
                    continue
                s: dict[str, Any] = {"subset": subset, "method": m, "spp": k, "images": len(sel)}
                for name in metric_names:
                    vals = [r[name] for r in sel]
                    s[name] = None if any(v is None for v in vals) else finite_or_none(float(np.mean(vals)))
                secs = [r["seconds"] for r in sel]
                total_mp = sum(mpix[r["image"]] for r in sel)
                s["ms_per_mpix"] = None if any(t is None for t in secs) else 1e3 * sum(secs) / total_mp
                out.append(s)
    return out


def write_csv(path: Path, rows: list[dict[str, Any]], metric_names: list[str]) -> None:
    """One row per image x spp x method; floats as ``repr`` (they read back exactly), null as empty."""
    with atomic_file(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        cols = [*CSV_FIELDS, *metric_names]
        w.writerow(cols)
        for r in rows:
            w.writerow(["" if r[c] is None else repr(r[c]) if isinstance(r[c], float) else r[c] for c in cols])
