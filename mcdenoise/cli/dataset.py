"""Render a procedural training dataset with a scene-level split.

    mcdenoise dataset --count N --out DIR [--spp 8] [--ref-spp 1024] [--size 128] [--seed S]
                      [--shard i/n] [--frames K | --views K] [--kind indoor|outdoor] [--max-depth 6] [--rr-depth 5]
                      [--variant auto|llvm_ad_rgb|cuda_ad_rgb]
    mcdenoise dataset --merge --out DIR

A rerun with the same options resumes: finished image folders are kept, leftovers of a killed run
are removed. Shards (``--shard i/n``, e.g. one per array job) render disjoint images; copy their
folders into one DIR and run ``--merge`` to rebuild the manifest. ``--views K`` renders K camera
views of each scene from one scene load (its kernels compile once): the cheap way to more images.
Mitsuba's CUDA variant is used where a GPU is present (``--variant`` overrides); the variant used
is recorded in dataset.json and manifest.json (a GPU renders other pixels than a CPU for the same
seed), and a rerun must use the same one.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mcdenoise.errors import SceneError
from mcdenoise.render.dataset_config import parse_shard, parse_split


def parse_objects(text: str) -> tuple[int, int]:
    """``"10-50"`` -> (10, 50); ``"20"`` -> (20, 20)."""
    lo, _, hi = text.partition("-")
    try:
        a, b = int(lo), int(hi or lo)
    except ValueError:
        raise SceneError(f"--objects {text!r}: expected MIN-MAX, e.g. 10-50") from None
    if not 1 <= a <= b <= 1000:
        raise SceneError(f"--objects {text!r}: need 1 <= MIN <= MAX <= 1000")
    return a, b


def add_parser(p: argparse.ArgumentParser) -> None:
    from mcdenoise.cli.render import add_variant_argument

    p.add_argument("--out", type=Path, help="dataset folder (created; a rerun resumes it)")
    p.add_argument("--count", type=int, help="number of scenes to render (required unless --merge)")
    p.add_argument("--spp", type=int, default=8, help="samples per pixel of the per-sample input (default 8)")
    p.add_argument("--ref-spp", type=int, default=1024, help="samples per pixel of the reference; 0 = none (default 1024)")
    p.add_argument("--size", default="128", help="N or WIDTHxHEIGHT (default 128)")
    p.add_argument("--seed", type=int, default=0, help="dataset seed; scene i is drawn from (seed, i) (default 0)")
    p.add_argument("--shard", default="0/1", help="render only scenes with index %% n == i (default 0/1)")
    p.add_argument("--frames", type=int, default=1,
                   help="frames per scene along a camera path, with position and motion layers (default 1)")
    p.add_argument("--views", type=int, default=1,
                   help="camera views per scene, each its own image in the scene's split; kernels compile once per "
                        "scene (default 1)")
    add_variant_argument(p)
    p.add_argument("--kind", choices=("indoor", "outdoor"), default=None, help="only this kind of scene (default both)")
    p.add_argument("--world", choices=("classic", "rich", "detailed"), default="classic",
                   help="procedural world: classic; rich (window-lit rooms, small bright emitters, night, "
                        "exposure over 2.3 decades); detailed (rich plus fine surface detail: tiles, print, fabric, "
                        "speckle, wood grain, cobbles, varying roughness; docs/DATASETS.md) (default classic)")
    p.add_argument("--small-emitters", type=float, default=None, metavar="P",
                   help="rich and detailed worlds: probability that a scene keeps the small bright emitters it "
                        "drew, the rest of it unchanged (default: all kept; docs/DATASETS.md)")
    p.add_argument("--strong-dof", type=float, default=None, metavar="P",
                   help="probability that a scene is shot through a wide lens, its subject in focus and the "
                        "rest blurred by up to a few %% of the width (default: never; docs/DATASETS.md)")
    p.add_argument("--generator", type=int, default=None,
                   help="scene pipeline version (default: the latest; a dataset made by an older one names it "
                        "in dataset.json, and its recipe states it)")
    p.add_argument("--max-depth", type=int, default=6, help="path depth of input and reference (default 6)")
    p.add_argument("--rr-depth", type=int, default=5,
                   help="depth from which Russian roulette may end a path, input and reference (default 5, "
                        "Mitsuba's; 2 is cheaper and noisier per sample: docs/DATASETS.md)")
    p.add_argument("--objects", default="10-50", help="MIN-MAX objects per scene (default 10-50)")
    p.add_argument("--split", default="0.8,0.1,0.1", help="train,val,test fractions of scenes (default 0.8,0.1,0.1)")
    p.add_argument("--only-split", default=None, metavar="SPLIT[,SPLIT]",
                   help="render only the scenes the split puts in these splits (train, val, test), the same images "
                        "a full run renders; a later run without it renders the rest")
    p.add_argument("--merge", action="store_true",
                   help="only rebuild manifest.json from the image folders in --out (damaged images are left out)")
    p.add_argument("--verify", type=Path, metavar="DIR",
                   help="check every image under DIR against its checksums, list the damaged ones (exit 1 if any)")
    from mcdenoise.cli.render import add_safety_arguments

    add_safety_arguments(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mcdenoise.cli.render import parse_size
    from mcdenoise.render.procedural_dataset import DatasetConfig, rebuild_manifest, render_dataset

    if args.verify is not None:
        return _verify(args.verify)
    if args.out is None:
        raise SceneError("--out DIR is required (or --verify DIR)")
    if args.merge:
        from mcdenoise.data.verify import verify_image
        from mcdenoise.render.procedural_dataset import CONFIG_FILE, finished_paths
        from mcdenoise.data.format import read_json_document

        cfg_path = args.out / CONFIG_FILE
        if not cfg_path.is_file():
            raise SceneError(f"{cfg_path}: no such file (not a procedural dataset folder?)")
        cfg = DatasetConfig.from_json(read_json_document(cfg_path), cfg_path)
        done = set()
        for rel in sorted(finished_paths(args.out, cfg)):
            problem = verify_image(args.out / rel)
            if problem is None:
                done.add(rel)
            else:
                print(f"left out of the manifest: {problem}", file=sys.stderr)
        path = rebuild_manifest(args.out, done)
        from mcdenoise.data.dataset import Dataset

        print(repr(Dataset(args.out)))
        print(f"wrote {path}")
        return 0
    if args.count is None:
        raise SceneError("--count N is required (or --merge to rebuild the manifest)")
    from mcdenoise.render._mitsuba import set_variant

    variant = set_variant(args.variant)
    w, h = parse_size(args.size)
    shard, shards = parse_shard(args.shard)
    from mcdenoise.cli.render import check_seed, max_bytes

    check_seed(args.seed)
    cfg = DatasetConfig(
        count=args.count, seed=args.seed, spp=args.spp, ref_spp=args.ref_spp, width=w, height=h,
        frames=args.frames, max_depth=args.max_depth, rr_depth=args.rr_depth, kind=args.kind, fractions=parse_split(args.split),
        objects=parse_objects(args.objects), views=args.views, world=args.world, small_emitters=args.small_emitters,
        strong_dof=args.strong_dof,
        variant=variant, **({} if args.generator is None else {"generator": args.generator}),
    )
    splits = None if args.only_split is None else [s.strip() for s in args.only_split.split(",")]
    summary = render_dataset(args.out, cfg, shard=shard, shards=shards, progress=not args.no_progress,
                             log=lambda s: print(s, file=sys.stderr), nonfinite=args.nonfinite, max_bytes=max_bytes(args),
                             splits=splits)
    print(f"rendered {summary['rendered']} image(s) in {summary['seconds']:.1f} s, {summary['skipped']} already done; "
          f"manifest: {summary['manifest']}")
    return 0


def _verify(root: Path) -> int:
    """``--verify DIR``: every image folder under DIR read in full against its checksums."""
    from mcdenoise.data.verify import verify_tree

    if not root.is_dir():
        raise SceneError(f"{root}: no such folder")
    n, problems = verify_tree(root)
    for line in problems:
        print(line)
    print(f"{root}: {n} image(s) checked, {len(problems)} damaged", file=sys.stderr)
    return 1 if problems else 0
