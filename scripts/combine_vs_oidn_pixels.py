"""Where a combiner loses to OIDN 2.5.1 high on a Blender render: each candidate's relMSE and the
pixels where the combination's error exceeds OIDN's most, with the candidates and weights there.

    python scripts/combine_vs_oidn_pixels.py [--model combine-ens] [NAME ...]

NAME is a render of ``scripts/blender_seeds.py``'s cache (default: glass_128px_8spp_s0,
glass_128px_8spp_s9, room_128px_8spp_s4), scored against that cache's 1024-spp reference.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

CACHE = Path(__file__).resolve().parent.parent / ".pytest_cache" / "d" / "blender-cycles"


def _rgb(ch: dict[str, np.ndarray], layer: str) -> np.ndarray:
    return np.stack([ch[f"{layer}.{c}"] for c in "RGB"]).astype(np.float32)


def _rel(x: np.ndarray, r: np.ndarray) -> np.ndarray:
    return ((x - r) ** 2 / (r ** 2 + 1e-2)).mean(0)  # per pixel, as mcdenoise.eval.metrics.relmse


def main() -> None:
    from mcdenoise.infer.run import add_oidn
    from mcdenoise.infer.sources import from_exr
    from mcdenoise.io.exr import read_exr_file
    from mcdenoise.models.weights import load_denoiser

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", default=["glass_128px_8spp_s0", "glass_128px_8spp_s9", "room_128px_8spp_s4"])
    ap.add_argument("--model", default="combine-ens")
    ap.add_argument("--top", type=int, default=8)
    a = ap.parse_args()
    model = load_denoiser(a.model)[0].eval()
    for name in a.names:
        scene = name.split("_")[0]
        src = next(CACHE.glob(name + "_bd_*.exr"))
        ref = _rgb(read_exr_file(next(CACHE.glob(f"{scene}_128px_1024spp_s1_*.exr")))[1], "ViewLayer.Combined")
        inp = from_exr(src)
        inp.ensure_pixels()
        add_oidn(inp, list(model.names[:2]) if hasattr(model, "names") else ["oidn"])
        p = inp.pixels
        batch = {k: torch.from_numpy(np.ascontiguousarray(p[k]))[None].float() for k in model.required_channels()}
        with torch.no_grad():
            kernel = model.kernel_output(batch)  # a kernel model's candidate (ens_kpcn, kpcn), else None
            out, w = model(batch)[0].numpy(), model.weights(batch, kernel)[0].numpy()
        names = list(model.names)
        if kernel is not None:
            p = {**p, "kernel": kernel[0].numpy()}
            names.append("kernel")
        maps = {n: _rel(p[n], ref) for n in names if n != "radiance"} | {"combined": _rel(out, ref)}
        print(f"\n{name}: relMSE " + ", ".join(f"{k} {v.mean():.5f}" for k, v in maps.items())
              + f"; combined / oidn {maps['combined'].mean() / maps['oidn'].mean():.3f}")
        d = (maps["combined"] - maps["oidn"]).ravel()
        top = np.argsort(-d)[: a.top]
        print(f"  per-pixel excess over OIDN: sum {d.sum():.2f} (positive {d[d > 0].sum():.2f}, negative "
              f"{d[d < 0].sum():.2f}); top {a.top}: {d[top].sum():.2f}")
        for i in top:
            y, x = divmod(int(i), ref.shape[2])
            vals = " ".join(f"{n} {p[n][:, y, x].mean():.3g}" for n in names)
            ws = " ".join(f"{v:.2f}" for v in w[:, y, x])
            print(f"  ({y:3d},{x:3d}) ref {ref[:, y, x].mean():.3g} {vals} combined {out[:, y, x].mean():.3g} "
                  f"weights {ws} albedo max {p['albedo'][:, y, x].max():.3g} excess {d[i]:.3f}")


if __name__ == "__main__":
    main()
