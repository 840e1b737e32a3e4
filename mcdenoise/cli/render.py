"""Render per-sample buffers and a reference from a Mitsuba 3 scene into one image folder.

    mcdenoise render SCENE --spp 8 --ref-spp 4096 --size 256x256 --out DIR [--seed N]
                     [--max-depth D] [-D name=value ...]
    mcdenoise render --list

SCENE is a Mitsuba 3 XML file (0.6 files are upgraded by Mitsuba) or a built-in scene name.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from mcdenoise.errors import SceneError

MAX_SIZE = 16384


def parse_size(text: str) -> tuple[int, int]:
    """``"256x128"`` -> (256, 128) (width, height); ``"128"`` -> (128, 128)."""
    parts = text.lower().split("x")
    try:
        if len(parts) == 1:
            w = h = int(parts[0])
        elif len(parts) == 2:
            w, h = int(parts[0]), int(parts[1])
        else:
            raise ValueError
    except ValueError:
        raise SceneError(f"--size {text!r}: expected WIDTHxHEIGHT or N, e.g. 256x256") from None
    if not (1 <= w <= MAX_SIZE and 1 <= h <= MAX_SIZE):
        raise SceneError(f"--size {text!r}: width and height must be in [1, {MAX_SIZE}]")
    return w, h


def parse_defines(items: list[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise SceneError(f"-D {item!r}: expected name=value")
        out[name] = value
    return out


def add_variant_argument(p: argparse.ArgumentParser) -> None:
    """``--variant`` (shared with ``mcdenoise dataset``). The choices spell out
    ``mcdenoise.render._mitsuba.VARIANTS``: importing the render package here would make ``--help`` slow."""
    p.add_argument("--variant", choices=("auto", "llvm_ad_rgb", "cuda_ad_rgb"), default="auto",
                   help="Mitsuba variant: auto = cuda_ad_rgb when a GPU is present, else llvm_ad_rgb (default auto)")


def add_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", nargs="?", help="Mitsuba 3 scene file or built-in scene name (see --list)")
    p.add_argument("--list", action="store_true", help="list the built-in scenes and exit")
    p.add_argument("--out", type=Path, help="image folder to create")
    p.add_argument("--spp", type=int, default=8, help="samples per pixel of the per-sample input (default 8)")
    p.add_argument("--ref-spp", type=int, default=4096, help="samples per pixel of the reference; 0 = none (default 4096)")
    p.add_argument("--size", default=None,
                   help="WIDTHxHEIGHT or N: the film size the scene is loaded with, so the camera is the one "
                        "Mitsuba builds for it; refused for a film with a crop window (default: the scene "
                        "file's film, or its crop window; 256x256 for built-in scenes)")
    p.add_argument("--seed", type=int, default=0, help="sampler seed (the reference derives its own)")
    p.add_argument("--max-depth", type=int, default=6, help="Mitsuba max_depth of input and reference (default 6)")
    p.add_argument("-D", dest="defines", action="append", default=[], metavar="NAME=VALUE",
                   help="set a scene default ($NAME) like Mitsuba's own -D; repeatable")
    p.add_argument("--channels", default=None,
                   help="comma-separated per-sample channels to keep (default: all; radiance always)")
    p.add_argument("--position", action="store_true", help="also store per-pixel world positions in noisy.exr")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing image folder (only one mcdenoise wrote; anything else is refused)")
    add_safety_arguments(p)
    add_variant_argument(p)


def add_safety_arguments(p: argparse.ArgumentParser) -> None:
    """``--nonfinite`` and ``--max-gb`` (shared with ``mcdenoise dataset``)."""
    p.add_argument("--nonfinite", choices=("sanitize", "error"), default="sanitize",
                   help="NaN/Inf samples: sanitize = replace by 0 and warn with the count; error = refuse (default sanitize)")
    p.add_argument("--max-gb", type=float, default=64.0,
                   help="refuse output larger than this many GB (free disk space is always checked; default 64)")


def check_seed(seed: int, flag: str = "--seed") -> int:
    """Seeds are 32-bit: a larger one would silently equal another, so it is refused."""
    if not 0 <= seed < 2**32:
        raise SceneError(f"{flag} {seed}: must be in [0, {2**32 - 1}] (seeds are 32-bit)")
    return seed


def max_bytes(args: argparse.Namespace) -> int | None:
    if not args.max_gb > 0:
        raise SceneError(f"--max-gb {args.max_gb}: must be a positive number of GB")
    return None if args.max_gb == float("inf") else int(args.max_gb * 1e9)


def run(args: argparse.Namespace) -> int:
    from mcdenoise.render import RenderSettings, builtin_motion, list_builtin_scenes, load_scene, render_image

    builtins = list_builtin_scenes()
    if args.list:
        width = max(len(n) for n in builtins)
        for name, desc in builtins.items():
            print(f"{name:<{width}}  {desc}")
        return 0
    if not args.scene:
        raise SceneError("no scene given (a Mitsuba 3 XML file or a built-in name; see --list)")
    if args.out is None:
        raise SceneError("--out DIR is required")
    from mcdenoise.io.safety import check_output_path

    check_seed(args.seed)
    limit = max_bytes(args)
    check_output_path(args.out, overwrite=args.overwrite)  # before paying for the scene load
    from mcdenoise.render._mitsuba import set_variant

    set_variant(args.variant)
    size = parse_size(args.size) if args.size else None
    defines = parse_defines(args.defines)
    channels = tuple(c.strip() for c in args.channels.split(",") if c.strip()) if args.channels else None
    # Refuse bad numbers before paying for the scene load.
    RenderSettings(spp=args.spp, ref_spp=args.ref_spp, max_depth=args.max_depth, channels=channels).check()
    extra = builtin_motion(args.scene) if args.scene in builtins else {}
    t0 = time.perf_counter()
    scene = load_scene(args.scene, defines=defines, width=size[0] if size else None, height=size[1] if size else None)
    # The rendered image is the film's crop window (the whole film when it has none).
    film = scene.sensors()[0].film().crop_size()
    w, h = int(film[0]), int(film[1])
    settings = RenderSettings(spp=args.spp, ref_spp=args.ref_spp, width=w, height=h, seed=args.seed,
                              max_depth=args.max_depth, channels=channels, **extra)
    settings.check()
    name = args.scene if args.scene in builtins else Path(args.scene).stem
    out = render_image(scene, args.out, settings, scene_name=name, record_position=args.position,
                       overwrite=args.overwrite, progress=True, extra_meta={"source": str(args.scene), "defines": defines},
                       nonfinite=args.nonfinite, max_bytes=limit)
    print(f"wrote {out} ({w}x{h}, {settings.spp} spp, reference {settings.ref_spp} spp) "
          f"in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0
