"""A training and validation set rendered with Cycles: Blender users' inputs, with references.

    python -m mcdenoise.render.cycles.dataset --out data/cycles_ref --count 48 --seed 301 \\
        --spp 4 8 16 --ref-spp 256 --size 128 --split 0.85,0.15,0 [--threads 1]

Scene ``i`` is drawn from (seed, i) (:mod:`mcdenoise.render.cycles.draw`), rendered by a worker
process at each input spp and at ``ref-spp`` with docs/DENOISE.md's Blender 4.x recipe (every
denoising and light pass), and converted with the same code that reads a user's file
(:func:`mcdenoise.data.convert.image_from_exr`): ``OUT/scene_0000/spp004/`` is an image folder of
the 4-spp render with the reference beside it. These images have no per-sample data, so pixel
models (``combine``, ``kpcn`` ``pixel``) train on them; each spp is its own image of the scene,
and every image of a scene is in the scene's split.

Resumable: a rerun skips scenes whose image folders verify, and refuses other settings than the
folder's ``dataset.json``. The same Blender version renders the same files (fixed seeds, CPU).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from mcdenoise.data.dataset import Dataset, assign_splits, write_manifest
from mcdenoise.errors import McDenoiseError
from mcdenoise.io.atomic import atomic_file
from mcdenoise.render.dataset_config import parse_shard, parse_split

__all__ = ["CONFIG_FORMAT", "scene_name", "image_path", "recipe_command", "render_cycles_dataset", "parser", "main"]

CONFIG_FORMAT = "mcdenoise-cycles-dataset"
CONFIG_FILE = "dataset.json"


def scene_name(index: int) -> str:
    return f"scene_{index:04d}"


def image_path(index: int, spp: int) -> str:
    return f"{scene_name(index)}/spp{spp:03d}"


def blender_version(python: str = sys.executable) -> str:
    """``bpy``'s version in ``python`` (a process of its own: bpy must not load beside pyoidn)."""
    done = subprocess.run([python, "-c", "import bpy; print(bpy.app.version_string)"], capture_output=True, text=True)
    if done.returncode != 0:
        raise McDenoiseError(f"{python}: cannot import bpy (pip install 'mcdenoise[blender]'): "
                             f"{done.stderr.strip().splitlines()[-1] if done.stderr.strip() else 'no message'}")
    return done.stdout.strip().splitlines()[-1]


def _config(args: argparse.Namespace, version: str) -> dict[str, Any]:
    return {"format": CONFIG_FORMAT, "version": 1, "seed": args.seed, "count": args.count, "spp": sorted(args.spp),
            "ref_spp": args.ref_spp, "size": args.size, "fractions": list(args.split), "blender": version}


def recipe_command(root: str | Path, cfg: dict[str, Any]) -> str:
    """The command that renders the dataset at ``root`` again, from its dataset.json ``cfg`` (which
    also records the bpy version: the same version gives the same files)."""
    split = ",".join(f"{f:g}" for f in cfg["fractions"])
    return (f"python -m mcdenoise.render.cycles.dataset --out {root} --count {cfg['count']} --seed {cfg['seed']} "
            f"--spp {' '.join(map(str, cfg['spp']))} --ref-spp {cfg['ref_spp']} --size {cfg['size']} --split {split}")


def _check_config(root: Path, cfg: dict[str, Any]) -> None:
    path = root / CONFIG_FILE
    if path.is_file():
        old = json.loads(path.read_text())
        same = {k: v for k, v in old.items() if k != "count"} == {k: v for k, v in cfg.items() if k != "count"}
        if not same:
            raise McDenoiseError(f"{path}: this folder was rendered with other settings ({old}); "
                                 f"use another --out or the same settings")
    root.mkdir(parents=True, exist_ok=True)
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(cfg, indent=1) + "\n")


def _scene_done(root: Path, index: int, spps: list[int]) -> bool:
    from mcdenoise.data.verify import verify_image

    return all((root / image_path(index, k)).is_dir() and verify_image(root / image_path(index, k)) is None
               for k in spps)


def _convert(root: Path, work: Path, index: int, spps: list[int], renderer: str) -> None:
    import warnings

    from mcdenoise.data.convert import image_from_exr
    from mcdenoise.io.blender import BlenderNote

    warnings.simplefilter("ignore", BlenderNote)  # "no Noisy Image: denoising Combined" is expected here
    desc = json.loads((work / "scene.json").read_text())
    for k in spps:
        folder = root / image_path(index, k)
        if folder.exists():
            shutil.rmtree(folder)  # left by a killed run (it did not verify)
        image_from_exr([work / f"spp{k}.exr"], folder, spp=k, reference=[work / "ref.exr"], scene=scene_name(index),
                       renderer=renderer, extra={"cycles_scene": desc})


def _manifest(root: Path, done: list[int], spps: list[int], cfg: dict[str, Any]) -> Path:
    scenes = [scene_name(i) for i in range(cfg["count"])]
    split = assign_splits(scenes, tuple(cfg["fractions"]), cfg["seed"])
    entries = [{"path": image_path(i, k), "scene": scene_name(i), "split": split[scene_name(i)], "index": i, "spp": k}
               for i in sorted(done) for k in spps]
    return write_manifest(root, entries, settings={k: v for k, v in cfg.items() if k not in ("format", "version")})


def render_cycles_dataset(args: argparse.Namespace, log=print) -> dict[str, Any]:
    root: Path = args.out
    version = blender_version()
    cfg = _config(args, version)
    _check_config(root, cfg)
    spps = cfg["spp"]
    done = [i for i in range(args.count) if _scene_done(root, i, spps)]
    t0, rendered = time.perf_counter(), 0
    for i in range(args.count):
        if i in done or i % args.shard[1] != args.shard[0]:
            continue
        work = root / ".work" / scene_name(i)
        cmd = [sys.executable, "-m", "mcdenoise.render.cycles.worker", "--seed", str(args.seed), "--index", str(i),
               "--spp", *map(str, spps), "--ref-spp", str(args.ref_spp), "--size", str(args.size),
               "--threads", str(args.threads), "--out", str(work)]
        res = subprocess.run(cmd, capture_output=True, text=True)
        if res.returncode != 0:
            raise McDenoiseError(f"{work}: Cycles worker failed ({' '.join(cmd)}): {res.stderr.strip()[-2000:]}")
        _convert(root, work, i, spps, f"cycles {version}")
        shutil.rmtree(work)
        done.append(i)
        rendered += 1
        _manifest(root, done, spps, cfg)
        log(f"{scene_name(i)}: done ({len(done)} of {args.count}, {time.perf_counter() - t0:.0f} s this run)")
    path = _manifest(root, done, spps, cfg)
    if (root / ".work").is_dir() and not any((root / ".work").iterdir()):
        (root / ".work").rmdir()
    return {"rendered": rendered, "done": len(done), "seconds": time.perf_counter() - t0, "manifest": path}


def parser() -> argparse.ArgumentParser:
    """The command's arguments (also what a model card's dataset command parses back with)."""
    p = argparse.ArgumentParser(prog="python -m mcdenoise.render.cycles.dataset", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="dataset folder (created; a rerun resumes it)")
    p.add_argument("--count", type=int, required=True, help="scenes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--spp", type=int, nargs="+", default=[4, 8, 16], help="input samples per pixel, one image each")
    p.add_argument("--ref-spp", type=int, default=256)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--threads", type=int, default=1, help="Cycles threads per render (the pixels do not depend on it)")
    p.add_argument("--split", type=parse_split, default=(0.85, 0.15, 0.0), help="train,val,test fractions of scenes")
    p.add_argument("--shard", type=parse_shard, default=(0, 1), help="render only scenes with index %% n == i")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        summary = render_cycles_dataset(args, log=lambda s: print(s, file=sys.stderr, flush=True))
    except McDenoiseError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(repr(Dataset(args.out)))
    print(f"rendered {summary['rendered']} scene(s) in {summary['seconds']:.0f} s; {summary['done']} done; "
          f"manifest: {summary['manifest']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
