"""Probe (issue 20, speed): OIDN 2.5.1 with ``cleanAux`` on guides prefiltered by something cheaper
than OIDN's own guide filters (each costs about one OIDN ``high`` run at 1080p), at each colour
quality. relMSE relative to plain OIDN high (noisy guides), means over images, per folder group.

    python scripts/guide_prefilter_probe.py data/rich_val data/scene_inputs --spp 8
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.data.stats import pixel_stats
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.eval.oidn import oidn_denoise, oidn_prefilter
from oidn_variants_probe import print_table


def bilateral(al: np.ndarray, nr: np.ndarray, radius: int, sigma_s: float, sigma_r: float, iters: int = 1):
    """Joint bilateral of albedo and normal, weights from both (6 channels), (3,H,W) each."""
    g = torch.from_numpy(np.concatenate([al, nr]))[None].float()
    k = 2 * radius + 1
    for _ in range(iters):
        pad = F.pad(g, (radius,) * 4, mode="replicate")
        patches = F.unfold(pad, k).view(1, 6, k * k, *g.shape[-2:])
        d2 = ((patches - g[:, :, None]) ** 2).sum(1, keepdim=True)
        yy, xx = torch.meshgrid(torch.arange(-radius, radius + 1), torch.arange(-radius, radius + 1), indexing="ij")
        sp = torch.exp(-(yy ** 2 + xx ** 2).float() / (2 * sigma_s ** 2)).view(1, 1, k * k, 1, 1)
        w = sp * torch.exp(-d2 / (2 * sigma_r ** 2))
        g = (w * patches).sum(2) / w.sum(2)
    a, n = g[0, :3].numpy(), g[0, 3:].numpy()
    norm = np.linalg.norm(n, axis=0, keepdims=True)
    n = np.where(norm > 1e-6, n / np.maximum(norm, 1e-6), 0.0)
    return a.astype(np.float32), n.astype(np.float32)


def folders(roots):
    for r in roots:
        for m in sorted(Path(r).rglob("meta.json")):
            if (m.parent / "reference.exr").is_file():
                yield Path(r).name, m.parent


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("roots", nargs="*")
    ap.add_argument("--spp", nargs="+", type=int, default=[8])
    ap.add_argument("--gf", nargs="*", default=[], help="guide-filter weights to compare (OIDN high on its guides, passed as noisy)")
    ap.add_argument("--per-image", action="store_true", help="also print every image's PSNR per candidate")
    ap.add_argument("--cost", metavar="WEIGHTS", help="only time the guide filter WEIGHTS at 1920x1080 against OIDN high")
    ap.add_argument("--short", action="store_true", help="only OIDN high, high on OIDN-prefiltered guides (as noisy, both or one) and --gf")
    a = ap.parse_args()
    from guide_filter_net import load, prefilter_guides
    if a.cost:
        cost(load(a.cost))
        return
    nets = {Path(w).parent.name or w: load(w) for w in a.gf}
    rows: dict = {}
    for group, p in folders(a.roots):
        f = ImageFolder(p)
        ref = f.read_reference(["radiance"])["radiance"]
        for k in a.spp:
            smp = f.samples.read(["radiance", "albedo", "normal"], samples=list(range(k)))
            m = {n: pixel_stats(v)[0] for n, v in smp.items()}
            c, al, nr = m["radiance"], m["albedo"], m["normal"]
            pa, pn = oidn_prefilter(al, "albedo"), oidn_prefilter(nr, "normal")
            cand = {"high": oidn_denoise(c, al, nr, quality="high"),
                    "high~oidn": oidn_denoise(c, pa, pn, quality="high"),
                    # one guide prefiltered at a time: which of the two carries the gain
                    "high~oidn-albedo-only": oidn_denoise(c, pa, nr, quality="high"),
                    "high~oidn-normal-only": oidn_denoise(c, al, pn, quality="high")}
            for name, net in nets.items():
                cand[f"high~gf:{name}"] = oidn_denoise(c, *prefilter_guides(al, nr, net), quality="high")
            if not a.short:
                guides = {"oidn": (pa, pn),
                          "noisy": (al, nr),
                          "box3": bilateral(al, nr, 1, 1e3, 1e3),
                          "bil2_s.1": bilateral(al, nr, 2, 1.5, 0.1),
                          "bil2_s.3": bilateral(al, nr, 2, 1.5, 0.3),
                          "bil2_s.3x2": bilateral(al, nr, 2, 1.5, 0.3, 2)}
                for gname, (ga, gn) in guides.items():
                    for q in ("high", "balanced", "fast"):
                        if gname != "oidn" and q == "high" and gname not in ("bil2_s.3", "box3"):
                            continue
                        cand[f"{q}|{gname}"] = oidn_denoise(c, ga, gn, quality=q, clean_aux=True)
                    if gname in ("bil2_s.1", "bil2_s.3"):  # guides cleaner, still passed as noisy
                        cand[f"high~{gname}"] = oidn_denoise(c, ga, gn, quality="high")
            d = rows.setdefault((group, k), {})
            for n, x in cand.items():
                d.setdefault(n, []).append((float(relmse(x, ref)), float(psnr(x, ref))))
            if a.per_image:
                print(f"{p.name} {k} spp PSNR: " + ", ".join(f"{n} {v[-1][1]:.2f}" for n, v in d.items()))
    print_table(rows)


def cost(net) -> None:
    """Median seconds at 1920x1080 (2 torch threads): the guide filter in float32 and in bfloat16
    (channels-last, autocast), and OIDN high with both guides, in one run."""
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from _timing import median_time

    torch.set_num_threads(2)
    g = torch.Generator().manual_seed(0)
    a, n = torch.rand(1, 3, 1080, 1920, generator=g), torch.rand(1, 3, 1080, 1920, generator=g) * 2 - 1
    cl = net.to(memory_format=torch.channels_last)
    ac, nc = a.contiguous(memory_format=torch.channels_last), n.contiguous(memory_format=torch.channels_last)

    def bf16() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            cl(ac, nc)

    with torch.inference_mode():
        t32 = median_time(lambda: cl(ac, nc), 3, warmup=1)
        t16 = median_time(bf16, 3, warmup=1)
    c = a[0].numpy() * 4
    toidn = median_time(lambda: oidn_denoise(c, a[0].numpy(), n[0].numpy()), 3, warmup=1)
    print(f"1920x1080: guide filter float32 {t32:.3f} s, bfloat16 {t16:.3f} s; OIDN high {toidn:.3f} s "
          f"(ratios {t32 / toidn:.2f}, {t16 / toidn:.2f})")

if __name__ == "__main__":
    main()
