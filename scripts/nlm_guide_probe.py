"""Probe (issue 20, speed): OIDN 2.5.1 high on an albedo guide prefiltered by NL-means that uses
the guide's own per-pixel variance (the feature prefilter of Rousselle et al. 2012 and NFOR), as a
cheap stand-in for OIDN's albedo prefilter (about one OIDN run at 1080p). relMSE relative to
plain OIDN high (noisy guides) per image and spp, then means.

    .venv/bin/python scripts/nlm_guide_probe.py data/scene_inputs [--radius 2 3] [--cost]

Needs image folders with per-sample buffers (the variance comes from the samples) and references.
``--cost`` times the plain-PyTorch filter at 1920x1080 against OIDN high in the same process.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.data.stats import pixel_stats
from mcdenoise.eval.metrics import psnr, relmse
from mcdenoise.eval.oidn import oidn_denoise, oidn_prefilter


@torch.no_grad()
def nlm_guide(u: torch.Tensor, var: torch.Tensor, radius: int = 3, patch: int = 1, k: float = 1.0,
              eps: float = 1e-4) -> torch.Tensor:
    """NL-means of a guide ``u`` (1, C, H, W) with its variance of the mean ``var`` (1, C, H, W):
    weight exp(-max(0, d)) with the variance-cancelled distance
    d = mean over channels and a (2*patch+1)^2 patch of ((u_p - u_q)^2 - (v_p + min(v_p, v_q))) / (eps + k^2 (v_p + v_q))."""
    h, w = u.shape[-2:]
    r = radius
    up, vp = F.pad(u, (r,) * 4, mode="replicate"), F.pad(var, (r,) * 4, mode="replicate")
    acc, wsum = torch.zeros_like(u), torch.zeros_like(u[:, :1])
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            uq, vq = up[..., r + dy:r + dy + h, r + dx:r + dx + w], vp[..., r + dy:r + dy + h, r + dx:r + dx + w]
            d = (((u - uq) ** 2 - (var + torch.minimum(var, vq))) / (eps + k * k * (var + vq))).mean(1, keepdim=True)
            if patch:
                d = F.avg_pool2d(F.pad(d, (patch,) * 4, mode="replicate"), 2 * patch + 1, stride=1)
            wt = torch.exp(-d.clamp_min(0))
            acc += wt * uq
            wsum += wt
    return acc / wsum


def cost(radii: list[int]) -> None:
    torch.set_num_threads(2)
    u, v = torch.rand(1, 3, 1080, 1920), torch.rand(1, 3, 1080, 1920) * 1e-3
    c = np.random.default_rng(0).random((3, 1080, 1920), dtype=np.float32)

    def med(f) -> float:
        ts = []
        for _ in range(3):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return float(np.median(ts))
    base = med(lambda: oidn_denoise(c, u[0].numpy(), u[0].numpy() * 2 - 1))
    print(f"1920x1080, torch 2 threads: OIDN high {base:.3f} s")
    for r in radii:
        t = med(lambda: nlm_guide(u, v, radius=r))
        print(f"  NL-means albedo, radius {r}: {t:.3f} s = {t / base:.2f}x OIDN high")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", nargs="*", type=Path)
    ap.add_argument("--radius", nargs="+", type=int, default=[2, 3])
    ap.add_argument("--cost", action="store_true")
    a = ap.parse_args()
    if a.cost:
        cost(a.radius)
        return
    rows: dict[tuple[int, str], list[tuple[float, float]]] = {}
    for root in a.roots:
        for m in sorted(root.rglob("meta.json")):
            if not (m.parent / "reference.exr").is_file():
                continue
            f = ImageFolder(m.parent)
            ref = f.read_reference(["radiance"])["radiance"]
            for spp in (4, 8, 16):
                st = {n: pixel_stats(x) for n, x in f.samples.read(["radiance", "albedo", "normal"], samples=list(range(spp))).items()}
                c, (al, alv), nr = st["radiance"][0], st["albedo"], st["normal"][0]
                base = oidn_denoise(c, al, nr)
                cand = {"oidn-albedo-prefilter": oidn_denoise(c, oidn_prefilter(al, "albedo"), nr)}
                for r in a.radius:
                    g = nlm_guide(torch.from_numpy(al)[None].double(), torch.from_numpy(alv)[None].double(), radius=r)
                    cand[f"nlm-r{r}"] = oidn_denoise(c, g[0].float().numpy(), nr)
                rb, pb = float(relmse(base, ref)), float(psnr(base, ref))
                line = []
                for n, x in cand.items():
                    rows.setdefault((spp, n), []).append((float(relmse(x, ref)) / rb, float(psnr(x, ref)) - pb))
                    line.append(f"{n} {rows[(spp, n)][-1][0]:.3f}")
                print(f"{m.parent.name[:24]:<24} {spp:>2} spp  " + ", ".join(line))
    for (spp, n), v in sorted(rows.items()):
        r = np.array([x[0] for x in v])
        print(f"{spp:>2} spp {n:<22} median ratio {np.median(r):.3f}, worst {r.max():.3f} ({int(r.argmax())}), "
              f"better on {(r < 1).sum()}/{len(r)}, mean dPSNR {np.mean([x[1] for x in v]):+.3f}")


if __name__ == "__main__":
    main()
