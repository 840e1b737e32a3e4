"""Where one denoiser's relMSE exceeds another's, by what the pixel shows: its roughness, whether it
sees the background, how textured its albedo is, how flat the reference is around it, how bright
it is against the image.

Reads a report written with ``mcdenoise eval ... --data DATASET --save-images`` and the dataset's
``noisy.exr`` files for the features (their 16-spp means; the eval's 4-spp inputs are a subset of
the same samples). For each feature the pixels are put in bins; per bin it prints the share of
pixels, each method's share of its own error, and the ratio A / B of the error summed over the bin.
Every image weighs the same: its per-pixel errors are divided by B's mean relMSE on that image
first, so one dark, noisy image does not decide the table.

    python scripts/gap_by_feature.py reports/c35_studio_images data/studio_plain layer-medium oidn-high --spp 4
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mcdenoise.io.exr import read_exr

EPS = 0.01  # the relMSE's, mcdenoise/eval/metrics.py

#: feature -> bin edges (a value v falls in bin i when edges[i] <= v < edges[i+1]).
BINS: dict[str, list[float]] = {
    "roughness": [0.0, 0.05, 0.2, 0.5, 1.01],
    "background": [0.0, 0.5, 1.5],
    "albedo_texture": [0.0, 0.01, 0.03, 0.1, np.inf],
    "reference_flatness": [0.0, 0.02, 0.05, 0.15, 0.5, np.inf],
    "brightness": [0.0, 0.25, 0.5, 1.0, 2.0, 4.0, np.inf],
}


def _lum(x: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` -> ``(H, W)`` Rec. 709 luminance."""
    return 0.2126 * x[0] + 0.7152 * x[1] + 0.0722 * x[2]


def _local_mad(x: np.ndarray) -> np.ndarray:
    """``(H, W)`` -> same: mean absolute difference to the 4 neighbours (the edge repeated)."""
    p = np.pad(x, 1, mode="edge")
    return (np.abs(p[1:-1, 2:] - x) + np.abs(p[1:-1, :-2] - x) + np.abs(p[2:, 1:-1] - x)
            + np.abs(p[:-2, 1:-1] - x)) / 4


def features(noisy: dict[str, np.ndarray], reference: np.ndarray) -> dict[str, np.ndarray]:
    """The per-pixel ``(H, W)`` features binned by :data:`BINS`."""
    ref_l = _lum(reference)
    alb_l = _lum(noisy["albedo"])
    return {
        "roughness": noisy["roughness"][0],
        # No first hit: the camera ray left the scene (depth 0 by the writer's convention).
        "background": (noisy["depth"][0] <= 0).astype(np.float64),
        "albedo_texture": _local_mad(alb_l),
        "reference_flatness": _local_mad(ref_l) / (ref_l + EPS),
        "brightness": ref_l / max(float(np.median(ref_l)), 1e-6),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="eval --save-images output folder")
    ap.add_argument("dataset", type=Path, help="the dataset the report evaluated")
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--spp", type=int, default=4)
    args = ap.parse_args(argv)

    refs = sorted((args.report / "images").rglob("reference.exr"))
    if not refs:
        raise SystemExit(f"{args.report}: no images/**/reference.exr (was the eval run with --save-images?)")
    sums = {f: np.zeros((3, len(e) - 1)) for f, e in BINS.items()}  # pixels, error A, error B
    for ref_path in refs:
        folder = ref_path.parent
        rel = folder.relative_to(args.report / "images")
        # The report's first folder is the dataset's name.
        noisy_path = args.dataset / Path(*rel.parts[1:]) / "noisy.exr"
        ref = read_exr(ref_path)
        ref = ref.get("radiance", ref.get("image"))
        outs = []
        for m in (args.a, args.b):
            o = read_exr(folder / f"{args.spp}spp" / f"{m}.exr")
            outs.append(o.get("radiance", o.get("image")))
        err = [((o - ref) ** 2 / (ref ** 2 + EPS)).mean(axis=0) for o in outs]
        scale = float(err[1].mean())
        feats = features(read_exr(noisy_path), ref)
        for f, edges in BINS.items():
            idx = np.digitize(feats[f], edges) - 1
            for i in range(len(edges) - 1):
                m = idx == i
                sums[f][0, i] += m.mean()
                sums[f][1, i] += err[0][m].sum() / err[0].size / scale
                sums[f][2, i] += err[1][m].sum() / err[1].size / scale
    n = len(refs)
    print(f"{n} images, {args.spp} spp; error shares and ratio {args.a} / {args.b}, each image scaled by "
          f"{args.b}'s relMSE")
    for f, edges in BINS.items():
        print(f"\n{f}: bin | pixels | share of {args.a} | share of {args.b} | ratio")
        tot = sums[f][1:].sum(axis=1)
        for i in range(len(edges) - 1):
            p, ea, eb = sums[f][:, i]
            if p == 0:
                continue
            print(f"  [{edges[i]:g}, {edges[i + 1]:g}) | {p / n:6.3f} | {ea / tot[0]:6.3f} | {eb / tot[1]:6.3f} | "
                  f"{ea / eb if eb else float('nan'):6.3f}")
    print(f"\nall: ratio {sums['roughness'][1].sum() / sums['roughness'][2].sum():.3f}")


if __name__ == "__main__":
    main()
