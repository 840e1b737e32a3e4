"""Export a denoiser to ONNX or TorchScript for use outside Python (a renderer plug-in, a C++ host).

    mcdenoise export --model NAME|WEIGHTS --format onnx|torchscript -o FILE [--size HxW] [--spp N]

The file takes the model's input channels as positional tensors (listed in ``FILE.json`` with
their shapes) and returns ``(1, 3, H, W)`` radiance. It is checked against PyTorch before it is
kept; a model that cannot export says so in one line naming the op. See docs/DENOISE.md.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from mcdenoise.errors import McDenoiseError


def add_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, help="registered name (its shipped weights), .safetensors file or run folder")
    p.add_argument("--format", required=True, choices=("onnx", "torchscript"), help="file format")
    p.add_argument("-o", "--output", type=Path, required=True, help="file to write (FILE.json describes its inputs)")
    p.add_argument("--size", default="256x256",
                   help="window HxW the export is traced at (default 256x256); FILE.json says whether other sizes work")
    p.add_argument("--spp", type=int, default=8, help="samples per pixel traced for the sample models (default 8)")
    p.add_argument("--force", action="store_true", help="replace an existing FILE")


def run(args: argparse.Namespace) -> int:
    from mcdenoise.infer.export import export_model
    from mcdenoise.models.weights import load_denoiser

    m = re.fullmatch(r"(\d+)[xX](\d+)", args.size)
    if m is None or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise McDenoiseError(f"--size: expected HxW, e.g. 256x256, got {args.size!r}")
    if args.spp < 1:
        raise McDenoiseError(f"--spp: must be positive, got {args.spp}")
    if args.output.exists() and not args.force:
        raise McDenoiseError(f"{args.output}: already exists; pass --force to replace it")
    model, info = load_denoiser(args.model, device="cpu")
    desc = export_model(model, args.output, args.format, example_size=(int(m.group(1)), int(m.group(2))),
                        spp=args.spp)
    sizes = "any size" if desc["any_size"] else f"windows of exactly {desc['size'][0]}x{desc['size'][1]}" + (
        f" at {desc['spp']} spp" if desc["spp"] else "")
    print(f"wrote {args.output} ({args.format}, model {info['name']} {info['preset']}; runs on {sizes}; "
          f"matches PyTorch to {desc['check_relative_error']:.1e} relative)")
    print(f"inputs: {', '.join(i['name'] for i in desc['inputs'])} (shapes in {args.output}.json)")
    return 0
