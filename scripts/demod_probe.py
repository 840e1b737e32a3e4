"""Would filtering a model's output as irradiance help? A learning-free probe (campaign 35).

For each image of an ``mcdenoise eval ... --save-images`` report, the model's output ``y`` is
demodulated by the effective albedo ``a`` of the eval's own input samples (wskp's rule,
:func:`mcdenoise.models.wskp.effective_albedo`), box-filtered over ``(2r+1)^2`` pixels and
modulated back: ``a * box_r(y / a)``. Beside it, the plain ``box_r(y)`` (the control: smoothing
alone), the albedo's detail put back on rough pixels (``y a / box_r(a)``: would undo a blurred
texture), and the per-pixel best of ``y`` and the demodulated one (what a perfect per-pixel selector
could reach; a bound, not a method). It also prints the share of dark-albedo pixels and how far the
eval's albedo strays from every sample's mean. relMSE as ``mcdenoise eval`` computes it; the geometric
mean of per-image ratios to ``y``'s.

    python scripts/demod_probe.py reports/c35_studio_images data/studio_plain layer-medium --spp 4
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

import mcdenoise  # noqa: F401  (sets up the package's defaults)
from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.eval.methods import Inputs
from mcdenoise.io.exr import read_exr
from mcdenoise.models.refine import blur
from mcdenoise.models.wskp import effective_albedo

EPS = 0.01  # the relMSE's, mcdenoise/eval/metrics.py
THRESHOLD = 0.05  # wskp's default (mcdenoise/models/wskp.py)


def box(x: np.ndarray, r: int) -> np.ndarray:
    """``(C, H, W)`` -> same: the mean over ``(2r+1)^2`` pixels, the edge repeated (the second
    stage's :func:`~mcdenoise.models.refine.blur` at factor ``r + 1``), in float64."""
    return blur(torch.from_numpy(x)[None].double(), r + 1)[0].numpy()


def pixel_relmse(y: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` pair -> ``(H, W)`` relMSE per pixel (mean over channels)."""
    return ((y - ref) ** 2 / (ref ** 2 + EPS)).mean(axis=0)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path)
    ap.add_argument("dataset", type=Path)
    ap.add_argument("method")
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--radii", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args(argv)
    refs = sorted((args.report / "images").rglob("reference.exr"))
    if not refs:
        raise SystemExit(f"{args.report}: no images/**/reference.exr (was the eval run with --save-images?)")
    logs: dict[str, list[float]] = {}
    dark, albedo_dev, albedo_mean = [], [], []
    for ref_path in refs:
        rel = ref_path.parent.relative_to(args.report / "images")
        x = Inputs(ImageFolder(args.dataset / Path(*rel.parts[1:])), args.spp)
        a = effective_albedo(torch.from_numpy(x.guides["albedo"])[None].double(),
                             torch.from_numpy(x.guides["normal"])[None].double(), THRESHOLD)[0].numpy()
        full = x.folder.read_noisy()["albedo"]  # every sample's mean: how far the eval's k-sample albedo strays
        dark.append(float((x.guides["albedo"].max(axis=0) < THRESHOLD).mean()))
        albedo_dev.append(float(np.abs(x.guides["albedo"] - full).mean()))
        albedo_mean.append(float(full.mean()))
        ref = read_exr(ref_path)["radiance"].astype(np.float64)
        y = read_exr(ref_path.parent / f"{args.spp}spp" / f"{args.method}.exr")["radiance"].astype(np.float64)
        e0 = pixel_relmse(y, ref)
        # Rough pixels only for the texture line: a glossy pixel's radiance is not albedo times light.
        has_roughness = "roughness" in x.folder.meta.channels
        rough = x.model_inputs(["roughness"], "pixels")["roughness"] > 0.5 if has_roughness else True
        for r in args.radii:
            ed = pixel_relmse(a * box(y / a, r), ref)
            # Texture put back: if y blurred the albedo's detail (y ~ box(a) E), y a / box(a) restores it.
            tex = np.where(rough, y * a / box(a, r), y)
            for name, e in ((f"demod box r{r}", ed), (f"texture back r{r} (rough px)", pixel_relmse(tex, ref)),
                            (f"plain box r{r}", pixel_relmse(box(y, r), ref)),
                            (f"best of y and demod r{r} (bound)", np.minimum(e0, ed))):
                logs.setdefault(name, []).append(float(np.log(e.mean() / e0.mean())))
    print(f"{len(refs)} images, {args.spp} spp, {args.method}: geometric mean of relMSE ratios to its output")
    print(f"  pixels with albedo below {THRESHOLD} in every channel: {np.mean(dark):.3f}; the {args.spp}-sample "
          f"albedo's mean absolute difference to all samples' mean: {np.sum(albedo_dev) / np.sum(albedo_mean):.3f} "
          f"of the latter's mean")
    for name, v in logs.items():
        print(f"  {name:34s} {np.exp(np.mean(v)):.4f}  (better on {sum(t < 0 for t in v)} of {len(v)})")


if __name__ == "__main__":
    main()
