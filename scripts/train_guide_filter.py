"""Train the guide prefilter (``scripts/guide_filter_net.py``, an experiment, not shipped) by distilling OIDN 2.5.1's guide filters.

Inputs: the mean albedo and normal of the first ``k`` samples of each image (``k`` drawn from
``--spp``), targets: what OIDN's albedo and normal filters make of those very guides. No
reference is needed, so any rendered dataset serves; the validation images are never trained on
(a dataset with a manifest gives its train split to ``--data`` and its val split to ``--val``).
Resumable: ``OUT/state.pt`` (weights-only load) holds the weights, optimiser and step; the pairs are
cached in ``OUT/pairs.npz`` (deterministic from the arguments).

    python scripts/train_guide_filter.py --data data/rich256 data/rich_ref data/rich_ref2 \
        --val data/rich_val --out runs/guide_filter --steps 3000
    python scripts/guide_prefilter_probe.py data/scene_inputs data/rich_val --spp 4 8 16 --short \
        --gf runs/guide_filter/guide_filter.safetensors
"""
from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.data.stats import pixel_stats
from guide_filter_net import GuideFilter
from mcdenoise.eval.oidn import oidn_prefilter


def image_folders(root: Path, split: str | None = None) -> list[Path]:
    """Image folders with samples under ``root``; only those of ``split`` where the dataset's
    manifest names splits (so a dataset's val images can validate without being trained on)."""
    man = root / "manifest.json"
    if split is not None and man.is_file():
        rows = json.loads(man.read_text())["images"]
        return sorted(root / r["path"] for r in rows if r.get("split") == split and (root / r["path"] / "samples.bin").is_file())
    return sorted(m.parent for m in root.rglob("meta.json") if (m.parent / "samples.bin").is_file())


def make_pairs(folders: list[Path], spps: list[int], per_image: int, seed: int) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Inputs and targets, float16 ``(N, 6, H, W)`` per size group; returns flat lists by index."""
    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for i, p in enumerate(folders):
        f = ImageFolder(p)
        ks = sorted(rng.choice(spps, size=min(per_image, len(spps)), replace=False).tolist())
        smp = f.samples.read(["albedo", "normal"], samples=list(range(max(ks))))
        for k in ks:
            al, nr = (pixel_stats(smp[c][:k])[0] for c in ("albedo", "normal"))
            ta, tn = oidn_prefilter(al, "albedo"), oidn_prefilter(nr, "normal")
            xs.append(np.concatenate([al, nr]).astype(np.float16))
            ys.append(np.concatenate([ta, tn]).astype(np.float16))
        if i % 50 == 0:
            print(f"pairs: {i + 1}/{len(folders)} images", flush=True)
    return xs, ys


def crops(xs, ys, n: int, size: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    bx, by = [], []
    for _ in range(n):
        j = int(rng.integers(len(xs)))
        h, w = xs[j].shape[-2:]
        y0, x0 = int(rng.integers(h - size + 1)), int(rng.integers(w - size + 1))
        sl = (slice(None), slice(y0, y0 + size), slice(x0, x0 + size))
        x, y = xs[j][sl], ys[j][sl]
        if rng.random() < 0.5:  # flips keep normals meaningful only if x is negated too: flip rows only
            x, y = x[:, ::-1], y[:, ::-1]
        bx.append(np.ascontiguousarray(x)), by.append(np.ascontiguousarray(y))
    return torch.from_numpy(np.stack(bx).astype(np.float32)), torch.from_numpy(np.stack(by).astype(np.float32))


def loss_fn(net: GuideFilter, x: torch.Tensor, y: torch.Tensor, l2: bool = True) -> torch.Tensor:
    """Squared error to OIDN's guides (default; L1 stalled at the identity: most pixels of a guide
    are clean, and L1's constant pull on them outweighs the few noisy ones), or L1 (the reported metric)."""
    a, n = net(x[:, :3], x[:, 3:])
    d = torch.cat([a - y[:, :3], n - y[:, 3:]], 1)
    return 2 * (d.square().mean() if l2 else d.abs().mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--val", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--spp", nargs="+", type=int, default=[1, 2, 4, 8, 16])
    ap.add_argument("--per-image", type=int, default=2)
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--c0", type=int, default=8)
    ap.add_argument("--c1", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "args.json").write_text(json.dumps(vars(a), indent=1))
    cache = out / "pairs.npz"
    if cache.is_file():
        z = np.load(cache)
        n = int(z["n"])
        xs, ys = [z[f"x{i}"] for i in range(n)], [z[f"y{i}"] for i in range(n)]
        vx, vy = [z[f"vx{i}"] for i in range(int(z["vn"]))], [z[f"vy{i}"] for i in range(int(z["vn"]))]
    else:
        folders = [p for d in a.data for p in image_folders(Path(d), "train")]
        xs, ys = make_pairs(folders, a.spp, a.per_image, a.seed)
        vx, vy = make_pairs(image_folders(Path(a.val), "val"), [2, 8], 2, a.seed + 1)
        tmp = out / ".pairs.tmp.npz"
        np.savez(tmp, n=len(xs), vn=len(vx), **{f"x{i}": x for i, x in enumerate(xs)}, **{f"y{i}": y for i, y in enumerate(ys)},
                 **{f"vx{i}": x for i, x in enumerate(vx)}, **{f"vy{i}": y for i, y in enumerate(vy)})
        os.replace(tmp, cache)
    print(f"{len(xs)} training pairs, {len(vx)} validation pairs", flush=True)
    torch.manual_seed(a.seed)
    net = GuideFilter(a.c0, a.c1)
    opt = torch.optim.Adam(net.parameters(), lr=a.lr)
    step = 0
    state = out / "state.pt"
    if state.is_file():
        st = torch.load(state, weights_only=True)
        net.load_state_dict(st["net"]), opt.load_state_dict(st["opt"])
        step = int(st["step"])
        print(f"resumed at step {step}", flush=True)

    def validate() -> tuple[float, float]:
        with torch.no_grad():
            l = ident = 0.0
            for x, y in zip(vx, vy):
                x, y = torch.from_numpy(x.astype(np.float32))[None], torch.from_numpy(y.astype(np.float32))[None]
                l += float(loss_fn(net, x, y, l2=False))
                ident += float((x - y).abs().mean() * 2)
        return l / len(vx), ident / len(vx)

    rng = np.random.default_rng(a.seed + 1000 + step)
    t0 = time.time()
    while step < a.steps:
        lr = a.lr * 0.5 * (1 + math.cos(math.pi * step / a.steps))
        for g in opt.param_groups:
            g["lr"] = lr
        x, y = crops(xs, ys, a.batch, a.crop, rng)
        loss = loss_fn(net, x, y)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        if step % 250 == 0 or step == a.steps:
            v, ident = validate()
            print(f"step {step} loss {float(loss.detach()):.5f} val L1 {v:.4f} (identity {ident:.4f}) {time.time() - t0:.0f}s", flush=True)
            tmp = out / ".state.tmp"
            torch.save({"net": net.state_dict(), "opt": opt.state_dict(), "step": step}, tmp)
            os.replace(tmp, state)
    from safetensors.torch import save_file

    tmp = out / ".gf.tmp"
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(tmp), metadata={"steps": str(step), "args": json.dumps(vars(a))})
    os.replace(tmp, out / "guide_filter.safetensors")
    print("wrote", out / "guide_filter.safetensors")


if __name__ == "__main__":
    main()
