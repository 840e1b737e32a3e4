"""Measure inference time, peak memory and FLOP use of every model beside OIDN 2.5.1, and training throughput.

    mcdenoise bench                              # the full run (< 15 min on 2 cores), Markdown on stdout
    mcdenoise bench --quick                      # 256x256, 1 and 8 spp, the target models (< 2 min)
    mcdenoise bench --models wskp:paper kpcn --json --out bench.json
    mcdenoise bench --device cuda                # synchronised GPU timing (OIDN stays on the CPU)
    mcdenoise bench --docs docs/PERFORMANCE.md   # also replace the generated block there

Methods are NAME (the small preset), NAME:PRESET, oidn (quality high) or oidn:fast; OIDN high and
fast are always added. A model with shipped weights is also timed through the public API
(`mcdenoise.denoise(...)`, as NAME:PRESET api) beside its bare call; --no-api leaves that out.
Rounds are interleaved over methods; see docs/PERFORMANCE.md.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size {text!r}: expected WIDTHxHEIGHT, e.g. 1920x1080") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size {text!r}: width and height must be >= 1")
    return w, h


def add_parser(p: argparse.ArgumentParser) -> None:
    # No torch import here (every `mcdenoise` command builds this parser).
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = __doc__.split("\n\n", 1)[1]
    p.add_argument("--quick", action="store_true", help="256x256, 1 and 8 spp, 2 rounds, OIDN + wskp:paper, kpcn, layer_optimized, sbmc")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of Markdown")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="where the models run (default cpu)")
    p.add_argument("--models", nargs="+", metavar="NAME[:PRESET]", help="methods (default: every model's small preset, wskp:paper, layer_optimized:paper_timed)")
    p.add_argument("--out", type=Path, help="also write the results here (.json: JSON, else Markdown)")
    p.add_argument("--docs", type=Path, help="replace the generated block 'bench:DEVICE' of this Markdown file")
    p.add_argument("--sizes", nargs="+", type=_size, metavar="WxH", help="image sizes (default 256x256 1280x720 1920x1080)")
    p.add_argument("--spp", nargs="+", type=int, help="spp for sample models (default 1 4 8 16 32)")
    p.add_argument("--rounds", type=int, help="timed rounds (default 3; quick 2)")
    p.add_argument("--budget", type=float, help="estimated seconds for the sizes after the first (default 300)")
    p.add_argument("--train-steps", type=int, help="timed training steps per model (default 3; 0 = no training figure)")
    p.add_argument("--threads", type=int, help="torch and OIDN threads alike (default: torch's, OIDN every core)")
    p.add_argument("--precision", choices=("float32", "bfloat16", "auto"), default="auto",
                   help="convolution trunks: auto (bfloat16 where the device has it natively; default), float32, bfloat16")
    p.add_argument("--reference", action="store_true", help="time the reference paths (no RepVGG folding, no_grad)")
    p.add_argument("--no-api", action="store_true",
                   help="do not also time mcdenoise.denoise() for the models with shipped weights")
    p.add_argument("--from-json", type=Path, metavar="FILE", help="no measuring: print/write the tables of a saved --out FILE.json")


def run(args: argparse.Namespace) -> int:
    import torch

    from mcdenoise.bench.plan import DEFAULT_METHODS, full_config, parse_method, quick_config
    from mcdenoise.bench.report import markdown
    from mcdenoise.bench.run import run_bench
    from mcdenoise.errors import McDenoiseError
    from mcdenoise.models.registry import list_models

    if args.device == "cuda" and not torch.cuda.is_available():
        raise McDenoiseError("--device cuda: no CUDA device is available")
    if args.threads:
        torch.set_num_threads(args.threads)
    over: dict[str, object] = {"device": args.device, "fast": not args.reference, "precision": args.precision,
                               "oidn_threads": args.threads or None, "api": not args.no_api}
    if args.models:
        known = {e.name for e in list_models()} | {"oidn"}
        methods = [parse_method(t) for t in dict.fromkeys([*DEFAULT_METHODS, *args.models])]
        bad = sorted({m.name for m in methods} - known)
        if bad:
            raise McDenoiseError(f"unknown model(s) {', '.join(bad)}; registered: {', '.join(sorted(known))}")
        presets = {e.name: e.presets for e in list_models()}
        for m in methods:
            if not m.is_oidn and m.preset not in presets[m.name]:
                raise McDenoiseError(f"model {m.name} has no preset {m.preset!r}; presets: {', '.join(sorted(presets[m.name]))}")
            if m.is_oidn:
                from mcdenoise.eval.oidn import parse_quality

                parse_quality(m.preset)  # OIDNError (one line) for an unknown quality
        over["methods"] = methods
    for flag, field in (("sizes", "sizes"), ("spp", "spp"), ("rounds", "rounds"), ("budget", "budget_s"),
                        ("train_steps", "train_steps")):
        v = getattr(args, flag)
        if v is not None:
            over[field] = tuple(v) if isinstance(v, list) else v
    if args.spp is not None and min(args.spp) < 1:
        raise McDenoiseError("--spp values must be >= 1")
    if args.from_json is not None:
        try:
            res = json.loads(args.from_json.read_text())
        except (OSError, ValueError) as e:
            raise McDenoiseError(f"--from-json {args.from_json}: {e}") from None
        command = res.get("command", "")
    else:
        cfg = quick_config(**over) if args.quick else full_config(**over)
        cfg.sizes = tuple(sorted(cfg.sizes, key=lambda s: s[0] * s[1]))
        res = run_bench(cfg)
        command = "mcdenoise bench " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if sys.argv[1:2] == ["bench"] else ""
        res["command"] = command
    from mcdenoise.io.safety import atomic_file

    if args.out is not None and args.out.suffix == ".json":  # first: the tables can be remade from it
        with atomic_file(args.out) as tmp:
            tmp.write_text(json.dumps(res, indent=1) + "\n")
    text = markdown(res, command)
    if args.out is not None and args.out.suffix != ".json":
        with atomic_file(args.out) as tmp:
            tmp.write_text(text + "\n")
    if args.docs is not None:
        from mcdenoise.eval.docblock import replace_block

        device = str(res["config"]["device"]).split(":")[0]
        replace_block(args.docs, f"bench:{device}", text, heading="## Denoiser speed (`mcdenoise bench`)")
    print(json.dumps(res, indent=1) if args.json else text)
    return 0


if __name__ == "__main__":  # pragma: no cover
    from mcdenoise.cli.main import main

    sys.exit(main(["bench", *sys.argv[1:]]))
