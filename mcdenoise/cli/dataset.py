"""Render a procedural training dataset with a scene-level split.

    mcdenoise dataset --count N --out DIR [--spp 8] [--ref-spp 1024] [--size 128] [--seed S]
                      [--shard i/n] [--frames K | --views K] [--kind indoor|outdoor] [--max-depth 6]
                      [--variant auto|llvm_ad_rgb|cuda_ad_rgb]
    mcdenoise dataset --merge --out DIR

A rerun with the same options resumes: finished image folders are kept, leftovers of a killed run
are removed. Shards (``--shard i/n``, e.g. one per array job) render disjoint images; copy their
folders into one DIR and run ``--merge`` to rebuild the manifest. ``--views K`` renders K camera
views of each scene from one scene load (its kernels compile once): the cheap way to more images.
Mitsuba's CUDA variant is used where a GPU is present (``--variant`` overrides).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mcdenoise.errors import SceneError


def parse_shard(text: str) -> tuple[int, int]:
    """``"2/8"`` -> (2, 8), checked: 0 <= i < n."""
    i, sep, n = text.partition("/")
    try:
        if not sep:
            raise ValueError
        a, b = int(i), int(n)
    except ValueError:
        raise SceneError(f"--shard {text!r}: expected i/n, e.g. 0/4") from None
    if b < 1 or not 0 <= a < b:
        raise SceneError(f"--shard {text!r}: need 0 <= i < n")
    return a, b


def parse_split(text: str) -> tuple[float, float, float]:
    try:
        parts = tuple(float(x) for x in text.split(","))
    except ValueError:
        parts = ()
    if len(parts) != 3 or min(parts) < 0 or sum(parts) <= 0:
        raise SceneError(f"--split {text!r}: expected three non-negative fractions train,val,test, e.g. 0.8,0.1,0.1")
    return parts  # type: ignore[return-value]


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

    p.add_argument("--out", type=Path, required=True, help="dataset folder (created; a rerun resumes it)")
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
    p.add_argument("--max-depth", type=int, default=6, help="path depth of input and reference (default 6)")
    p.add_argument("--objects", default="10-50", help="MIN-MAX objects per scene (default 10-50)")
    p.add_argument("--split", default="0.8,0.1,0.1", help="train,val,test fractions of scenes (default 0.8,0.1,0.1)")
    p.add_argument("--merge", action="store_true", help="only rebuild manifest.json from the image folders in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mcdenoise.cli.render import parse_size
    from mcdenoise.render.procedural_dataset import DatasetConfig, rebuild_manifest, render_dataset

    if args.merge:
        path = rebuild_manifest(args.out)
        from mcdenoise.data.dataset import Dataset

        print(repr(Dataset(args.out)))
        print(f"wrote {path}")
        return 0
    if args.count is None:
        raise SceneError("--count N is required (or --merge to rebuild the manifest)")
    from mcdenoise.render._mitsuba import set_variant

    set_variant(args.variant)
    w, h = parse_size(args.size)
    shard, shards = parse_shard(args.shard)
    cfg = DatasetConfig(
        count=args.count, seed=args.seed, spp=args.spp, ref_spp=args.ref_spp, width=w, height=h,
        frames=args.frames, max_depth=args.max_depth, kind=args.kind, fractions=parse_split(args.split),
        objects=parse_objects(args.objects), views=args.views,
    )
    summary = render_dataset(args.out, cfg, shard=shard, shards=shards, progress=not args.no_progress,
                             log=lambda s: print(s, file=sys.stderr))
    print(f"rendered {summary['rendered']} image(s) in {summary['seconds']:.1f} s, {summary['skipped']} already done; "
          f"manifest: {summary['manifest']}")
    return 0
