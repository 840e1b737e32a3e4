"""Clean or noisy training targets at equal CPU time (issue 9 item 3).

    python benchmarks/bench_noisy_targets.py WORK_DIR [--model kpcn] [--size 64] [--images 4 4 4 16]
        [--steps 200] [--lr 1e-3] [--crop 24] [--batch 4] [--val 3]

Three arms train the same model on the same procedural scenes (dataset seed 1, so arm X's first
n scenes are arm Y's first n scenes) and are validated on the same separate val images (seed 100,
8 spp input, 1024-spp references; not counted in any budget):

* ``ref1024`` / ``ref128``: 8 spp input, reference.exr at that spp, ``--target reference``;
* ``noisy``: 16 spp stored, no reference; each crop's input is 8 random samples and its target the
  mean of the other 8 (``--target noisy``); ``noisy_more``: the same with more scenes;
* ``ref1024_16``: 16 spp stored with 1024-spp references, input 8 random samples (``--spp 8 8``).
  It separates the two things the noisy arm changes: the reference arms always see the same 8-spp
  noise realisation of a pixel, the noisy arm a new subset of 16 samples per crop.

Cost is CPU seconds (user + system, children included, from ``getrusage``), so a loaded machine
changes the wall time but much less the accounting. The budget is what ``ref1024`` spends: its
dataset render plus ``--steps`` training steps. Every other arm gets the same total; what its
cheaper render saved buys more steps at ``ref1024``'s measured CPU seconds per step. All arms use
the same loss (``relmse``, unbiased for noisy targets) and, for KPCN/DPCN, no per-branch phase
(``log(1 + specular)`` of a noisy target would be biased).

Pools are rendered with ``mcdenoise dataset`` into WORK_DIR and reused by later runs (their CPU
cost is stored next to them in ``t_<pool>``). Prints one line per arm and writes ``results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
from pathlib import Path

from mcdenoise.data.dataset import Dataset, write_manifest
from mcdenoise.train.runlog import METRICS_FILE, read_metrics

BIN = [str(Path(sys.executable).parent / "mcdenoise")]


def _child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(cmd: list[str], log: Path) -> float:
    """Run ``cmd`` to completion; returns its CPU seconds (it and its children)."""
    before = _child_cpu()
    with open(log, "w") as f:
        subprocess.run(cmd, check=True, stdout=f, stderr=subprocess.STDOUT)
    return _child_cpu() - before


def render_pool(work: Path, name: str, *, count: int, spp: int, ref_spp: int, seed: int, split: str, size: int) -> float:
    """Render (or reuse) pool ``name`` of at least ``count`` images; returns CPU seconds per image."""
    stamp = work / f"t_{name}"
    if stamp.is_file() and (work / name / "manifest.json").is_file():
        have = len(Dataset(work / name))
        if have < count:
            raise SystemExit(f"{work / name}: {have} images, {count} needed; delete it (and {stamp}) to re-render")
        parts = stamp.read_text().split()  # "<name> cpu <user> <sys> wall <s>" (also GNU time's -f)
        return (float(parts[2]) + float(parts[3])) / have
    cpu = _run(BIN + ["dataset", "--out", str(work / name), "--count", str(count), "--spp", str(spp),
                      "--ref-spp", str(ref_spp), "--seed", str(seed), "--split", split, "--size", str(size),
                      "--no-progress"], work / f"log_{name}")
    stamp.write_text(f"{name} cpu {cpu:.2f} 0 wall 0\n")
    return cpu / count


def arm_folder(work: Path, arm: str, pool: str, n: int) -> Path:
    """``work/arm_<arm>``: the first ``n`` train images of ``pool`` plus the shared val images (links)."""
    out = work / f"arm_{arm}"
    out.mkdir(exist_ok=True)
    entries = []
    for src_name, split, limit in ((pool, "train", n), ("val", "val", None)):
        src = Dataset(work / src_name)
        for e in src.entries[:limit]:
            link = out / f"{src_name}_{e['path'].replace('/', '_')}"
            if not link.exists():
                os.symlink((work / src_name / e["path"]).resolve(), link)
            entries.append({"path": link.name, "scene": f"{src_name}:{e['scene']}", "split": split})
    write_manifest(out, entries)
    return out


def train_arm(work: Path, arm: str, data: Path, a: argparse.Namespace, steps: int, target: str,
              spp: tuple[int, int] | None) -> tuple[float, dict[str, str]]:
    run = work / f"run_{arm}"
    cmd = BIN + ["train", "--model", a.model, "--data", str(data), "--out", str(run), "--steps", str(steps),
                 "--crop", str(a.crop), "--batch", str(a.batch), "--loss", "relmse", "--target", target,
                 "--workers", str(a.workers), "--val-every", "0", "--val-images", str(a.val), "--seed", str(a.seed),
                 "--lr", str(a.lr), "--force", "--no-progress"]
    if a.model in ("kpcn", "dpcn"):
        cmd += ["--branch-fraction", "0"]
    if spp is not None:
        cmd += ["--spp", str(spp[0]), str(spp[1])]
    cpu = _run(cmd, work / f"log_run_{arm}")
    return cpu, [r for r in read_metrics(run / METRICS_FILE) if r["val_relmse"]][-1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("work", type=Path)
    p.add_argument("--model", default="kpcn")
    p.add_argument("--size", type=int, default=64)
    p.add_argument("--images", type=int, nargs=4, default=[4, 4, 4, 16], metavar=("REF1024", "REF128", "NOISY", "NOISY_MORE"),
                   help="train images per arm (noisy_more: the noisy arm with more scenes)")
    p.add_argument("--steps", type=int, default=200, help="training steps of the ref1024 arm (sets the budget)")
    p.add_argument("--lr", type=float, default=1e-3, help="peak learning rate of every arm (short runs need more than the papers')")
    p.add_argument("--crop", type=int, default=24)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--val", type=int, default=3, help="validation images (1024 spp references)")
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    size = a.size
    render_pool(a.work, "val", count=a.val, spp=8, ref_spp=1024, seed=100, split="0,1,0", size=size)
    arms = [  # (arm, pool, images, stored spp, reference spp, target, input spp range)
        ("ref1024", "poolA", a.images[0], 8, 1024, "reference", None),
        ("ref128", "poolB", a.images[1], 8, 128, "reference", None),
        ("noisy", "poolC", a.images[2], 16, 0, "noisy", None),
        ("noisy_more", "poolC", a.images[3], 16, 0, "noisy", None),
        ("ref1024_16", "poolD", a.images[0], 16, 1024, "reference", (8, 8)),
    ]
    # One pool per render setting, as large as its largest arm; an arm is charged its share.
    pools: dict[str, tuple[int, int, int]] = {}
    for _, pool, n, spp, ref, _, _ in arms:
        pools[pool] = (max(n, pools.get(pool, (0,))[0]), spp, ref)
    per_image = {}
    for pool, (count, spp, ref) in pools.items():
        per_image[pool] = render_pool(a.work, pool, count=count, spp=spp, ref_spp=ref, seed=1, split="1,0,0", size=size)
    results = {}
    cpu_per_step = None
    budget = 0.0
    for arm, pool, n, _, _, target, spp_in in arms:
        render = per_image[pool] * n
        data = arm_folder(a.work, arm, pool, n)
        steps = a.steps if cpu_per_step is None else max(1, int((budget - render) / cpu_per_step))
        cpu, last = train_arm(a.work, arm, data, a, steps, target, spp_in)
        if cpu_per_step is None:
            cpu_per_step = cpu / steps
            budget = render + cpu
        results[arm] = {"images": n, "render_cpu_s": round(render, 1), "steps": steps, "train_cpu_s": round(cpu, 1),
                        "total_cpu_s": round(render + cpu, 1), "val_relmse": float(last["val_relmse"]),
                        "val_psnr": float(last["val_psnr"])}
        r = results[arm]
        print(f"{arm:10s} images={n:3d} render={r['render_cpu_s']:7.1f}s steps={steps:5d} train={r['train_cpu_s']:7.1f}s "
              f"total={r['total_cpu_s']:7.1f}s  val relMSE={r['val_relmse']:.4f}  PSNR={r['val_psnr']:.2f}", flush=True)
    (a.work / "results.json").write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
