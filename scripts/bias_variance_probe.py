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

``--by-luminance`` also splits each part over decades of the reference's luminance (campaign 35,
step 7): which pixels carry a method's variance. ``--spread-scale K`` feeds heads with the spread
features (``RefineConfig.spread``) K times the base's disagreement between its halves (0: none):
does the head act on where it reads the base's noise?
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
from mcdenoise.models import refine
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


def split_maps(outputs: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``outputs (n, 3, H, W)`` of disjoint sample sets, ``ref (3, H, W)`` -> per-pixel (bias, variance)
    maps ``(H, W)``, each the mean over channels of the module docstring's terms."""
    n = outputs.shape[0]
    w = 1.0 / (ref.astype(np.float64) ** 2 + EPS)
    y = outputs.astype(np.float64)
    m = y.mean(axis=0)
    var = w * ((y - m) ** 2).sum(axis=0) / (n - 1)
    bias = w * (m - ref) ** 2 - var / n
    return bias.mean(axis=0), var.mean(axis=0)


def split(outputs: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    """``outputs (n, 3, H, W)`` of disjoint sample sets, ``ref (3, H, W)`` -> (total, bias, variance):
    image means of the per-pixel terms of the module docstring; total = bias + variance."""
    return parts(*split_maps(outputs, ref))


def parts(bias: np.ndarray, var: np.ndarray) -> tuple[float, float, float]:
    """Per-pixel maps -> (total, bias, variance) image means."""
    return float(bias.mean() + var.mean()), float(bias.mean()), float(var.mean())


#: ``--by-luminance`` bins: the reference's luminance (mean of its channels) in decades.
LUMINANCE_EDGES = (0.0, 0.01, 0.1, 1.0, 10.0, np.inf)


def by_luminance(bias: np.ndarray, var: np.ndarray, ref: np.ndarray,
                 edges: tuple[float, ...] = LUMINANCE_EDGES) -> np.ndarray:
    """Per-pixel ``bias``/``var`` maps ``(H, W)`` and ``ref (3, H, W)`` -> ``(bins, 3)``: per luminance
    bin of the reference, the fraction of pixels and the bin's share of the image's bias and variance
    parts (its sum over the image's pixel count), so each part's shares add up to :func:`split`'s."""
    lum = ref.astype(np.float64).mean(axis=0)
    idx = np.clip(np.searchsorted(np.asarray(edges), lum, side="right") - 1, 0, len(edges) - 2)
    k, npx = len(edges) - 1, lum.size
    return np.stack([np.bincount(idx.ravel(), minlength=k) / npx,
                     np.bincount(idx.ravel(), bias.ravel(), minlength=k) / npx,
                     np.bincount(idx.ravel(), var.ravel(), minlength=k) / npx], axis=1)


def scale_spread(k: float) -> None:
    """From now on :func:`refine.spread_features` reads the two halves ``k`` times as far apart,
    about their mean (a probe, for this process only)."""
    orig = refine.spread_features

    def scaled(lum: torch.Tensor, half_a: torch.Tensor, half_b: torch.Tensor) -> torch.Tensor:
        mid = (half_a + half_b) / 2
        return orig(lum, mid + k * (half_a - mid), mid + k * (half_b - mid))

    refine.spread_features = scaled


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("roots", nargs="+", help="datasets (their --split images) or image folders")
    ap.add_argument("--models", nargs="*", default=[])
    ap.add_argument("--split", default="val")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--baseline", default="oidn-high")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--by-luminance", action="store_true",
                    help="also split each part over decades of the reference's luminance")
    ap.add_argument("--spread-scale", type=float, default=None, metavar="K",
                    help="spread-feature heads read K times the base's disagreement between halves")
    args = ap.parse_args(argv)
    if args.spread_scale is not None:
        scale_spread(args.spread_scale)
    methods = [ModelMethod(spec, *load_denoiser(spec), "cpu") for spec in args.models]
    images = [e.folder for e in collect_images(args.roots, split=args.split)[0]]
    per: dict[str, list[tuple[float, float, float]]] = {}
    bins: dict[str, list[np.ndarray]] = {}
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
            bias, var = split_maps(np.stack(ys), ref)
            per.setdefault(name, []).append(parts(bias, var))
            bins.setdefault(name, []).append(by_luminance(bias, var, ref))
    base = np.array(per[args.baseline])
    print(f"{len(images)} images, {args.spp} spp, {n} disjoint sample sets each; ratios to {args.baseline}, "
          f"each image divided by its total first")
    print(f"{'method':28s} {'total':>9s} {'bias':>9s} {'variance':>9s} | {'total':>6s} {'bias':>6s} {'var':>6s}")
    for name, v in per.items():
        v = np.array(v)
        r = (v / base[:, :1]).sum(axis=0) / base.shape[0]
        print(f"{name:28s} {v[:, 0].mean():9.5f} {v[:, 1].mean():9.5f} {v[:, 2].mean():9.5f} | "
              f"{r[0]:6.3f} {r[1]:6.3f} {r[2]:6.3f}")
    if args.by_luminance:
        e = LUMINANCE_EDGES
        labels = [f"{e[i]:g}-{e[i + 1]:g}" for i in range(len(e) - 1)]
        frac = np.mean([b[:, 0] for b in bins[args.baseline]], axis=0)
        print("\nby the reference's luminance (mean of its channels): each bin's share of the image's part, "
              "mean over images; the shares add up to the totals above")
        print(f"{'luminance':>12s} {'pixels':>7s} " + " ".join(f"{n[:17]:>17s}" for n in per if n != "noisy"))
        print(f"{'':>12s} {'':>7s} " + " ".join(f"{'bias':>8s} {'var':>8s}" for n in per if n != "noisy"))
        for i, lab in enumerate(labels):
            row = " ".join(f"{np.mean([b[i, 1] for b in bins[n]]):8.5f} {np.mean([b[i, 2] for b in bins[n]]):8.5f}"
                           for n in per if n != "noisy")
            print(f"{lab:>12s} {frac[i]:7.3f} {row}")


if __name__ == "__main__":
    main()
