"""Choose a model's ``consistency`` (issue 19, "never worse than the noisy input"): its
output clamped per pixel to ``k`` shrunk standard errors of the pixel's own samples
(:mod:`mcdenoise.models.consistency`; a pixel model's from the input's per-pixel variance, as
``denoise`` and ``eval`` apply it), for each ``k``, on held-out images at each spp. Prints the
geometric-mean and median relMSE, the mean PSNR, and on how many images the result is worse than
the noisy input. The rule it serves (docs/models/consistency.md): the ``k`` with the lowest sum
over spp of geometric-mean relMSE among those whose mean PSNR is nowhere below the model's
without the clamp.

    python scripts/consistency_probe.py data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val --models sbmc-small layer-small --spp 4 8 16 --ks 1.5 2 3 4

A ``k`` written ``K@N`` (``4@8``) clamps only from ``N`` samples per pixel (the configuration's
``consistency_min_spp``): below it the output is the unclamped one. ``Km`` (``4m``, ``4m@8``) takes
the median of the 5x5 box's variances instead of their mean (``consistency_box``). The last lines
apply the rule to each model: the eligible settings with their sums, and the choice; then, for the last
``k`` given, each later model paired with the first (the standing rule's figures, to 5 decimals).
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from mcdenoise.eval.images import collect_images
from mcdenoise.eval.methods import Inputs, ModelMethod
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.models import consistency
from mcdenoise.models.consistency import consistency_clamp, pixel_consistency_clamp
from mcdenoise.models.weights import load_denoiser


def parse_k(text: str) -> tuple[float, int, str]:
    """``"4"`` -> (4.0, 2, "mean"); ``"4m@8"`` -> (4.0, 8, "median"): k, the fewest spp it acts
    at (``consistency_min_spp``) and the neighbourhood's statistic (``consistency_box``)."""
    k, _, n = text.partition("@")
    box = "median" if k.endswith("m") else "mean"
    return float(k.removesuffix("m")), int(n) if n else 2, box


def k_label(k: float, first: int, box: str) -> str:
    return f"k {k:g}" + ("m" if box == "median" else "") + (f"@{first}" if first != 2 else "")


def rule_choice(figures: dict[str, dict[int, tuple[float, float]]]) -> tuple[list[str], str]:
    """The rule of docs/models/consistency.md on one model's ``figures`` (setting -> spp -> (geo-mean
    relMSE, mean PSNR), with ``"none"``): the eligible settings (mean PSNR nowhere below "none"'s),
    lowest sum of geo-mean relMSE over spp first, and the choice ("none" when none is eligible)."""
    base = figures["none"]
    ok = [key for key, f in figures.items()
          if key != "none" and set(f) == set(base) and all(f[s][1] >= base[s][1] for s in base)]
    ok.sort(key=lambda key: sum(v[0] for v in figures[key].values()))
    return ok, ok[0] if ok else "none"


def paired_lines(per_image: dict[tuple[str, str, int], np.ndarray], first: str, key: str = "k 4") -> list[str]:
    """The standing rule's paired figures, each model's setting ``key`` against ``first``'s, per spp:
    the ratio of geometric-mean relMSE, the mean PSNR difference to 5 decimals (the 4 of the
    per-model lines can tie), and on how many images the PSNR is higher. ``per_image[(model, key,
    spp)]`` is an (images, 2) array of (relMSE, PSNR) in one image order for every model."""
    lines = []
    for (name, k, spp), v in sorted(per_image.items(), key=lambda kv: (kv[0][2], kv[0][0])):
        base = per_image.get((first, key, spp))
        if name == first or k != key or base is None:
            continue
        ratio = float(np.exp(np.log(v[:, 0]).mean() - np.log(base[:, 0]).mean()))
        diff = float((v[:, 1] - base[:, 1]).mean())
        higher = int((v[:, 1] > base[:, 1]).sum())
        lines.append(f"paired spp {spp:2d} {name} {key} vs {first} {key}: relMSE geo ratio {ratio:.5f}, "
                     f"PSNR {diff:+.5f} dB, higher on {higher} of {len(v)}")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("roots", nargs="+")
    ap.add_argument("--models", nargs="+", required=True)
    ap.add_argument("--spp", nargs="+", type=int, default=[4, 8, 16])
    ap.add_argument("--ks", nargs="+", type=parse_k, default=[parse_k(k) for k in ("1.5", "2", "2.5", "3", "4")],
                    help="k, K@N to clamp only from N spp (consistency_min_spp), Km for the median box")
    ap.add_argument("--prior", type=float, default=None,
                    help="weight of the neighbourhood's variance in samples (default: the module's PRIOR; 0: none)")
    a = ap.parse_args()
    if a.prior is not None:
        consistency.PRIOR = a.prior  # read at each call: every bound below uses it
    # The val split of a dataset, every image of a folder of image folders (eval's own rule).
    images = [e.folder for e in collect_images(a.roots, split="val")[0]]
    methods = []
    for spec in a.models:
        m, info = load_denoiser(spec)
        methods.append(ModelMethod(info.get("label", spec), m, info, "cpu"))
    figures: dict[str, dict[str, dict[int, tuple[float, float]]]] = {}
    per_image: dict[tuple[str, str, int], np.ndarray] = {}
    for spp in a.spp:
        res: dict = {}
        for im in images:
            if im.samples is None:
                continue
            ref = im.read_reference(["radiance"])["radiance"]
            x = Inputs(im, spp)
            mu = x.guides["radiance"]
            r_noisy, p_noisy = relmse(mu, ref), psnr(mu, ref)
            for meth in methods:
                batch = meth.prepare(x)
                meth.model.config.consistency = None  # the model's own output, then each k on it
                out = torch.from_numpy(meth.run(batch))[None]
                r = res.setdefault(meth.name, {})
                r.setdefault("none", []).append((relmse(out[0].numpy(), ref), psnr(out[0].numpy(), ref), r_noisy, p_noisy))
                for k, first, box in a.ks:
                    if meth.model.input_kind == "samples":
                        c = consistency_clamp(out, batch["radiance"], k, first, box)[0].numpy()
                    else:  # what denoise and eval do after a pixel model: the k samples' statistics
                        c = pixel_consistency_clamp(out[0].numpy(), mu, x.guides["radiance_variance"], spp, k, first, box)
                    r.setdefault(k_label(k, first, box), []).append((relmse(c, ref), psnr(c, ref), r_noisy, p_noisy))
        for name, r in res.items():
            for key, v in r.items():
                v = np.array(v)
                per_image[(name, key, spp)] = v[:, :2]
                wr, wp = int((v[:, 0] >= v[:, 2]).sum()), int((v[:, 1] <= v[:, 3]).sum())
                figures.setdefault(name, {}).setdefault(key, {})[spp] = (float(np.exp(np.log(v[:, 0]).mean())),
                                                                           float(v[:, 1].mean()))
                print(f"spp {spp:2d} {name:12s} {key:8s}: relMSE geo {np.exp(np.log(v[:, 0]).mean()):.5f} median "
                      f"{np.median(v[:, 0]):.5f}  PSNR {v[:, 1].mean():.4f}  worse than noisy: relMSE {wr}, PSNR {wp} of {len(v)}",
                      flush=True)
    for name, f in figures.items():
        ok, choice = rule_choice(f)
        sums = ", ".join(f"{key} ({sum(v[0] for v in f[key].values()):.5f})" for key in ok)
        print(f"rule {name}: eligible {sums or 'none'}; choice {choice}")
    for line in paired_lines(per_image, methods[0].name, k_label(*a.ks[-1])):
        print(line)


if __name__ == "__main__":
    main()
