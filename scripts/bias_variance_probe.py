"""Is a denoiser's error residual noise or a wrong mean? A split of relMSE over disjoint sample sets
(campaign 35).

Each image's stored samples are cut into ``n`` disjoint sets of ``--spp`` (16 stored, 4 spp: 4 sets).
Every method denoises each set; per pixel, with ``y_j`` the outputs, ``m`` their mean and ``r`` the
reference (relMSE's weight ``w = 1 / (r^2 + 0.01)``, per channel):

    mean_j w (y_j - r)^2  =  w (m - r)^2 - w s^2 / n   +   w s^2,   s^2 = sum_j (y_j - m)^2 / (n - 1)

The last term is the **variance** (what another draw of the samples changes: noise the method left);
the first two are the **bias** (what every draw shares: detail smoothed away, a wrong level; it
includes the reference's own noise, the same for every method). Both are unbiased estimates. Per
method it prints the mean over images of the total and of each part, and each part's ratio to
``--baseline``'s (per image divided by the baseline's total, so every image weighs the same).

    python scripts/bias_variance_probe.py data/studio_plain --models layer-medium --spp 4
"""
from __future__ import annotations

import argparse
from typing import Any

import numpy as np
import torch

import mcdenoise  # noqa: F401  (sets up the package's defaults)
from mcdenoise.eval.images import collect_images
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.oidn import oidn_denoise
from mcdenoise.models.weights import load_denoiser

EPS = 0.01  # the relMSE's, mcdenoise/eval/metrics.py


class _Shifted:
    """A samples reader whose sample ``i`` is the wrapped reader's ``offset + i``."""

    def __init__(self, reader: Any, offset: int) -> None:
        self._reader, self._offset = reader, offset

    def read(self, names, *, samples=None, crop=None):  # noqa: ANN001, ANN201 (the reader's signature)
        return self._reader.read(names, samples=[self._offset + i for i in samples], crop=crop)


class SampleSet:
    """An image folder seen from sample ``offset`` on: :class:`Inputs` over it reads samples
    ``offset .. offset + k - 1`` (never ``noisy.exr``, which holds every sample's mean)."""

    def __init__(self, folder: Any, offset: int) -> None:
        self._folder, self.samples = folder, _Shifted(folder.samples, offset)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._folder, name)


def split(outputs: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    """``outputs (n, 3, H, W)`` of disjoint sample sets, ``ref (3, H, W)`` -> (total, bias, variance):
    image means of the per-pixel terms of the module docstring; total = bias + variance."""
    n = outputs.shape[0]
    w = 1.0 / (ref.astype(np.float64) ** 2 + EPS)
    y = outputs.astype(np.float64)
    m = y.mean(axis=0)
    s2 = ((y - m) ** 2).sum(axis=0) / (n - 1)
    var = float((w * s2).mean())
    bias = float((w * (m - ref) ** 2).mean()) - var / n
    return bias + var, bias, var


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("roots", nargs="+", help="datasets (their --split images) or image folders")
    ap.add_argument("--models", nargs="*", default=[])
    ap.add_argument("--split", default="val")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--baseline", default="oidn-high")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    methods = [ModelMethod(spec, *load_denoiser(spec), "cpu") for spec in args.models]
    images = [e.folder for e in collect_images(args.roots, split=args.split)[0]]
    per: dict[str, list[tuple[float, float, float]]] = {}
    for im in images:
        n = im.meta.spp // args.spp
        if n < 2 or im.samples is None:
            raise SystemExit(f"{im.path}: needs per-sample data with at least {2 * args.spp} samples")
        ref = im.read_reference(["radiance"])["radiance"]
        outs: dict[str, list[np.ndarray]] = {}
        for j in range(n):
            x = Inputs(SampleSet(im, j * args.spp), args.spp)
            g = x.guides
            outs.setdefault("noisy", []).append(g["radiance"])
            outs.setdefault("oidn-high", []).append(oidn_denoise(g["radiance"], g["albedo"], g["normal"],
                                                                 threads=args.threads))
            for meth in methods:
                with torch.inference_mode():
                    outs.setdefault(meth.name, []).append(meth.run(meth.prepare(x)))
        for name, ys in outs.items():
            per.setdefault(name, []).append(split(np.stack(ys), ref))
    base = np.array(per[args.baseline])
    print(f"{len(images)} images, {args.spp} spp, {n} disjoint sample sets each; ratios to {args.baseline}, "
          f"each image divided by its total first")
    print(f"{'method':28s} {'total':>9s} {'bias':>9s} {'variance':>9s} | {'total':>6s} {'bias':>6s} {'var':>6s}")
    for name, v in per.items():
        v = np.array(v)
        r = (v / base[:, :1]).sum(axis=0) / base.shape[0]
        print(f"{name:28s} {v[:, 0].mean():9.5f} {v[:, 1].mean():9.5f} {v[:, 2].mean():9.5f} | "
              f"{r[0]:6.3f} {r[1]:6.3f} {r[2]:6.3f}")


if __name__ == "__main__":
    main()
