"""Denoise an EXR (Blender, Mitsuba, pbrt or our naming), separate colour/albedo/normal files, or an image folder.

    mcdenoise denoise INPUT -o OUTPUT.exr [--model NAME|WEIGHTS] [--albedo F] [--normal F] [--depth F]
                      [--device cpu|cuda] [--tile auto|N] [--max-memory 4G] [--preview OUT.png] [--force]
                      [--replace-combined]

INPUT is a multi-layer EXR in any naming of ``mcdenoise/io/names.py``, a colour EXR with its
features in separate files (``--albedo``, ``--normal``, ``--depth``, as OIDN's tools take them),
or an image folder of ``mcdenoise render`` (whose per-sample buffers feed the sample models).
Without ``--model``: a shipped model whose inputs are present and whose card shows it beating OIDN
2.5.1 high on the third-party validation scenes, else OIDN itself (``--model oidn``); the command
says which, why, and which channels it read. The output holds the denoised radiance as top-level ``R, G, B``
(float32); a Blender multi-layer EXR is written back whole (every pass, alpha and header
attribute bit for bit) with the result added as the pass ``<ViewLayer>.Denoised``, or written into
``Combined`` with ``--replace-combined`` (``mcdenoise/io/blender.py``). Written atomically; the
input is never overwritten, nor an existing output without ``--force``. See docs/DENOISE.md.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import warnings
from pathlib import Path

from mcdenoise.errors import McDenoiseError


def add_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", type=Path, help="EXR file or image folder of `mcdenoise render`")
    p.add_argument("-o", "--output", type=Path, required=True, help="denoised EXR to write")
    p.add_argument("--model", default=None,
                   help="registered name (its shipped weights), oidn, .safetensors file or run folder; "
                        "default: the best for the channels present, OIDN unless a shipped model beats it on the validation scenes")
    p.add_argument("--albedo", type=Path, default=None, help="albedo image (EXR) when INPUT is only the colour")
    p.add_argument("--normal", type=Path, default=None, help="normal image (EXR) when INPUT is only the colour")
    p.add_argument("--depth", type=Path, default=None, help="depth image (single-channel EXR)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    p.add_argument("--precision", choices=("float32", "bfloat16", "auto"), default="auto",
                   help="convolution trunks: auto (default: bfloat16 where the CPU/GPU computes it natively, else float32), "
                        "float32, bfloat16; the shipped models' test metrics agree within 2%% (docs/PERFORMANCE.md); "
                        "eval defaults to float32, so its figures are the same on every CPU")
    p.add_argument("--tile", default="auto", help="tile side in pixels, or auto (sized from --max-memory)")
    p.add_argument("--max-memory", default="4G", help="memory budget of one tile, e.g. 4G or 512M (default 4G)")
    p.add_argument("--self-ensemble", action="store_true",
                   help="run the model on the 8 flips and quarter turns of the image and keep the per-pixel median: "
                        "8x the time, fewer exploded highlights (docs/DENOISE.md)")
    p.add_argument("--preview", type=Path, default=None, help="also write an 8-bit sRGB PNG preview here")
    p.add_argument("--force", action="store_true", help="replace an existing OUTPUT")
    p.add_argument("--replace-combined", action="store_true",
                   help="Blender input: write the result into the Combined pass instead of a new Denoised "
                        "pass (every other pass, the alpha and the header are kept either way)")


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` (existing or not, through any spelling or link) lies inside ``folder``."""
    try:
        return path.resolve().is_relative_to(folder.resolve())
    except (OSError, RuntimeError):
        return False


def _read_sources(args: argparse.Namespace, inputs: list[Path]) -> tuple[list[Path], list[Path]]:
    """``(files, folders)`` the command reads: the inputs, the weights or run folder of ``--model``,
    and the image folder holding an input file (meta.json beside it)."""
    sources = list(inputs)
    if args.model is not None and Path(args.model).exists():
        sources.append(Path(args.model))
    files = [p for p in sources if not p.is_dir()]
    folders = [p for p in sources if p.is_dir()]
    folders += [p.parent for p in files if (p.parent / "meta.json").is_file()]
    return files, folders


def _check_outputs(args: argparse.Namespace, inputs: list[Path]) -> None:
    """Refuse, before any work, outputs that would overwrite a file the command reads, land inside
    an input folder (image folder or run folder), or replace an existing file without --force."""
    out: Path = args.output
    if out.suffix.lower() != ".exr":
        raise McDenoiseError(f"{out}: the output must be an .exr file")
    targets = [("output", out)] + ([("preview", args.preview)] if args.preview is not None else [])
    files, folders = _read_sources(args, inputs)
    for what, path in targets:
        for src in files:
            if path.resolve() == src.resolve() or _same(path, src):
                raise McDenoiseError(f"{path}: the {what} would overwrite the input {src}; choose another name")
        for folder in folders:
            if _inside(path, folder):
                raise McDenoiseError(f"{path}: the {what} would be written inside the input folder {folder}, "
                                     "which is never written to (even with --force); choose a path outside it")
        if path.is_dir():
            raise McDenoiseError(f"{path}: is a folder, the {what} must be a file")
        if path.exists() and not args.force:
            raise McDenoiseError(f"{path}: already exists; pass --force to replace it")
    if args.preview is not None and (args.preview.resolve() == out.resolve() or _same(args.preview, out)):
        raise McDenoiseError(f"{out}: output and preview are the same file")


def _tile(text: str) -> int | str:
    if text == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise McDenoiseError(f"--tile: expected auto or a positive number of pixels, got {text!r}")
    return n


def run(args: argparse.Namespace) -> int:
    from mcdenoise.infer.memory import parse_memory

    tile = _tile(args.tile)
    try:
        budget = parse_memory(args.max_memory)
    except ValueError as e:
        raise McDenoiseError(f"--max-memory: {e}") from None
    src: Path = args.input
    if not src.exists():
        raise McDenoiseError(f"{src}: no such file or folder")
    extras = [p for p in (args.albedo, args.normal, args.depth) if p is not None]
    if src.is_dir() and extras:
        raise McDenoiseError(f"{src}: --albedo/--normal/--depth go with a colour EXR, not an image folder")
    for p in extras:
        if not p.is_file():
            raise McDenoiseError(f"{p}: no such file")
    _check_outputs(args, [src, *extras])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code = _denoise(args, src, tile, budget)
    for w in caught:
        first = str(w.message).strip().splitlines()
        print(f"mcdenoise denoise: warning: {first[0] if first else w.category.__name__}", file=sys.stderr)
    return code


def _denoise(args: argparse.Namespace, src: Path, tile: int | str, budget: int) -> int:
    import torch

    from mcdenoise.infer.choose import choose_model
    from mcdenoise.infer.run import default_device, denoise_inputs, describe_plan
    from mcdenoise.infer.sources import from_exr, from_folder
    from mcdenoise.io import blender
    from mcdenoise.io.exr import read_exr_file, tonemap, write_exr_file, write_exr_raw, write_png
    from mcdenoise.errors import OutputError
    from mcdenoise.io.safety import atomic_file, os_error, remove_stale_temps

    if args.device is not None and args.device.startswith("cuda") and not torch.cuda.is_available():
        raise McDenoiseError("--device cuda: no CUDA device is available (use --device cpu)")
    try:
        device = torch.device(args.device) if args.device else default_device()
    except RuntimeError as e:
        raise McDenoiseError(f"--device: {e}") from None
    if device.type not in ("cpu", "cuda"):
        raise McDenoiseError(f"--device {args.device}: not supported; use cpu or cuda")
    if src.is_dir():
        inputs = from_folder(src)
    else:
        inputs = from_exr(src, albedo=args.albedo, normal=args.normal, depth=args.depth)
    # A Blender file is written back whole, with the result as a pass of its own (io/blender.py).
    source = read_exr_file(src) if src.is_file() else None
    to_blender = source is not None and blender.is_cycles(list(source[1]))
    if args.replace_combined and not to_blender:
        raise McDenoiseError(f"{src}: --replace-combined needs a Blender multi-layer EXR (one with a view-layer "
                             f"'Combined' or 'Noisy Image' pass)")
    model, info = choose_model(inputs, args.model, device=device, precision=args.precision)
    print(f"model: {info['name']} ({info['preset']}, {info['source']} weights {info['weights']}; {info['why']}; "
          f"{info['precision']})")
    kind = "per-sample" if model.input_kind == "samples" else "per-pixel"
    print(f"channels: {', '.join(info['channels'])} ({kind})")
    out, run = denoise_inputs(inputs, model, device=device, tile=tile, max_memory=budget,
                              self_ensemble=args.self_ensemble)
    turns = f", in each of {run.orientations} orientations (per-pixel median)" if run.orientations > 1 else ""
    print(f"ran {describe_plan(run.plan)} on {run.device}{turns}")
    if args.self_ensemble and run.orientations == 1:
        print("self-ensemble: not applied (OIDN runs once, as its library does)")
    if run.consistency:
        print(f"consistency: {run.consistency}")
    attrs = {"mcdenoise_model": str(info["name"]), "mcdenoise_weights": str(info["weights"]),
             "mcdenoise_input": str(src)}
    if run.orientations > 1:  # says how the pixels were made: a re-run without the flag differs
        attrs["mcdenoise_self_ensemble"] = f"{run.orientations} orientations, per-pixel median"
    targets = [args.output] + ([args.preview] if args.preview is not None else [])
    for path in targets:
        remove_stale_temps(path)  # temporaries of a killed earlier run
    try:
        # Both files are written under temporary names and renamed only when both are written:
        # a preview that cannot be written leaves no EXR behind (nor the other way round).
        with contextlib.ExitStack() as stack:
            tmps = [stack.enter_context(atomic_file(path)) for path in targets]
            try:
                if to_blender:
                    assert source is not None
                    channels, header = blender.blender_output(source[1], source[0], out, path=src,
                                                              replace_combined=args.replace_combined)
                    write_exr_file(tmps[0], channels, {**header, **attrs})
                else:
                    write_exr_raw(tmps[0], {"R": out[0], "G": out[1], "B": out[2]}, attributes=attrs)
            except OutputError as e:  # named by its temporary name: name the output
                raise OutputError(args.output, e.problem) from None
            if args.preview is not None:
                import numpy as np

                try:
                    write_png(tmps[1], np.round(tonemap(out) * 255.0).astype(np.uint8).transpose(1, 2, 0))
                except OSError as e:
                    raise os_error(args.preview, e, "writing the preview") from None
    except OSError as e:
        raise McDenoiseError(f"{e.filename or args.output}: cannot write ({e.strerror or e})") from None
    for path in targets:
        print(f"wrote {path}")
    return 0
