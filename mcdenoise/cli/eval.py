"""Evaluate denoisers against the noisy input, OIDN 2.5.1 and NL-means; write an HTML report.

    mcdenoise eval --models A B ... (--data DIR [DIR ...] | --scenes DIR [--refs DIR]) --out REPORT_DIR [--split test]
                   [--spp 4 8 16] [--oidn high fast] [--no-oidn] [--no-classic] [--max-images N]
                   [--device auto|cpu|cuda] [--threads N]
                   [--results-md docs/RESULTS.md --section NAME]
                   [--no-html] [--save-images] [--no-progress]

A model is a registered name (its shipped weights), a run folder of `mcdenoise train`, or a
.safetensors file. DIR is a dataset folder (its --split images), an image folder from
`mcdenoise render`, or a folder of such image folders; only images with a reference count.
--scenes DIR is a folder of Mitsuba 3 scenes (NAME/scene.xml) with references in --refs
(NAME_<W>_spp<N>_d<D>.npy, default DIR/refs), as ../shared/valscenes: the inputs are rendered
once per --render-seed (at the largest --spp, the reference's size and max depth) into --work and
reused; the scenes folder is only read.
REPORT_DIR gets results.json, results.csv and index.html (see docs/EVAL.md); the terminal gets
the ranked summary the page leads with (per spp, best relMSE first, * marks each column's best).
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path


def add_parser(p: argparse.ArgumentParser) -> None:
    # No torch import here: every `mcdenoise` command builds this parser.
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = __doc__.split("\n\n", 1)[1]
    p.add_argument("--models", nargs="*", default=[], metavar="MODEL",
                   help="registered names (shipped weights), run folders or .safetensors files")
    p.add_argument("--data", nargs="+", default=[], metavar="DIR", help="dataset or image folders")
    p.add_argument("--scenes", type=Path, help="folder of scene files with references (see below)")
    p.add_argument("--refs", type=Path, help="references of --scenes (default SCENES/refs)")
    p.add_argument("--scene-names", nargs="+", metavar="NAME", help="only these scenes of --scenes")
    p.add_argument("--render-seed", type=int, nargs="+", default=[7], metavar="SEED",
                   help="sampler seed(s) of the --scenes inputs (default 7); several render each scene once per seed, "
                        "and the report adds the spread of the per-seed means")
    p.add_argument("--work", type=Path, default=Path("data/scene_inputs"),
                   help="where the --scenes inputs are rendered and kept (default data/scene_inputs)")
    p.add_argument("--out", type=Path, required=True, help="report folder (an earlier report there is replaced)")
    p.add_argument("--split", default="test", help="dataset split to evaluate (default test)")
    p.add_argument("--spp", type=int, nargs="*", default=[4, 8, 16], metavar="K",
                   help="input sample counts: the first K stored samples (default 4 8 16)")
    p.add_argument("--oidn", nargs="+", default=["high", "fast"], metavar="QUALITY",
                   help="OIDN qualities: high, balanced, fast, each optionally with -pf: guides prefiltered "
                        "by OIDN first, its best mode for noisy guides (default high fast)")
    p.add_argument("--no-oidn", action="store_true", help="leave OIDN out")
    p.add_argument("--no-classic", action="store_true", help="leave the NL-means filter out")
    p.add_argument("--max-images", type=int, help="at most N images per data folder")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="device of the models and NL-means (default auto: CUDA when available)")
    p.add_argument("--threads", type=int,
                   help="CPU threads of torch and OIDN alike (default: torch's, OIDN every core; 1 is faster on busy cores)")
    p.add_argument("--precision", nargs="+", default=["float32"], choices=("float32", "bfloat16", "auto"),
                   help="run every model in each: float32 (default, unlike denoise's auto: eval's figures must be the "
                        "same on every CPU), bfloat16 (convolution trunks; rows labelled +bf16), auto (as denoise)")
    p.add_argument("--self-ensemble", action="store_true",
                   help="also run every model on the 8 flips and quarter turns of each image, keeping the per-pixel "
                        "median (labelled MODEL+se; 8x the time)")
    p.add_argument("--results-md", type=Path, help="also write the tables into this Markdown file...")
    p.add_argument("--section", help="...as its generated block eval:SECTION")
    p.add_argument("--no-html", action="store_true", help="only results.json and results.csv")
    p.add_argument("--save-images", action="store_true",
                   help="also write every full-size output as OUT/images/IMAGE/Kspp/METHOD.exr (and reference.exr)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from mcdenoise.eval.runner import EvalError, evaluate

    data = list(args.data)
    if args.scenes is not None:
        from mcdenoise.eval.scenes import find_scene_cases, prepare_scene_inputs

        if not args.spp:
            raise EvalError("--scenes needs --spp")
        cases = find_scene_cases(args.scenes, args.refs, names=args.scene_names)
        if len(set(args.render_seed)) != len(args.render_seed):
            raise EvalError(f"--render-seed: a seed given twice ({' '.join(map(str, args.render_seed))})")
        for seed in args.render_seed:
            data += [str(p) for p in prepare_scene_inputs(cases, args.work, spp=max(args.spp), seed=seed,
                                                          progress=not args.no_progress)]
    if not data:
        raise EvalError("nothing to evaluate: give --data DIR ... or --scenes DIR")
    argv = sys.argv[1:] if Path(sys.argv[0]).name == "mcdenoise" and sys.argv[1:2] == ["eval"] else None
    command = "mcdenoise " + shlex.join(argv) if argv else _command_from(args)
    doc = evaluate(
        models=args.models,
        data=data,
        out=args.out,
        split=args.split,
        spp=args.spp,
        oidn=[] if args.no_oidn else args.oidn,
        classic=not args.no_classic,
        max_images=args.max_images,
        device=args.device,
        threads=args.threads,
        precision=args.precision,
        results_md=args.results_md,
        section=args.section,
        html=not args.no_html,
        progress=not args.no_progress,
        command=command,
        self_ensemble=args.self_ensemble,
        save_images=args.save_images,
    )
    from mcdenoise.eval.ranking import terminal_summary

    for note in doc["notes"]:
        if "labelled" in note:
            print(f"note: {note}", file=sys.stderr, flush=True)
    print(terminal_summary(doc))
    sys.stdout.flush()
    n = len({r["image"] for r in doc["rows"]})
    print(f"{args.out}: {n} images x spp {', '.join(map(str, doc['config']['spp']))}, "
          f"{len(doc['methods'])} methods" + (f"; {args.results_md} block eval:{args.section}" if args.results_md else ""),
          file=sys.stderr)
    return 0


def _command_from(args: argparse.Namespace) -> str:
    """The equivalent command line when not started as ``mcdenoise`` (tests, ``python -m``)."""
    parts = ["eval"]
    if args.models:
        parts += ["--models", *args.models]
    if args.data:
        parts += ["--data", *args.data]
    if args.scenes is not None:
        parts += ["--scenes", str(args.scenes)] + (["--refs", str(args.refs)] if args.refs else [])
        parts += (["--scene-names", *args.scene_names] if args.scene_names else []) + ["--render-seed", *map(str, args.render_seed)]
    parts += ["--split", args.split, "--spp", *map(str, args.spp), "--out", str(args.out)]
    if args.no_oidn:
        parts.append("--no-oidn")
    elif args.oidn != ["high", "fast"]:
        parts += ["--oidn", *args.oidn]
    if args.no_classic:
        parts.append("--no-classic")
    if args.max_images is not None:
        parts += ["--max-images", str(args.max_images)]
    if args.device != "auto":
        parts += ["--device", args.device]
    if args.threads is not None:
        parts += ["--threads", str(args.threads)]
    if args.precision != ["float32"]:
        parts += ["--precision", *args.precision]
    if args.self_ensemble:
        parts.append("--self-ensemble")
    if args.save_images:
        parts.append("--save-images")
    if args.results_md is not None:
        parts += ["--results-md", str(args.results_md), "--section", str(args.section)]
    return "mcdenoise " + shlex.join(parts)


if __name__ == "__main__":  # pragma: no cover
    from mcdenoise.cli.main import main

    sys.exit(main(["eval", *sys.argv[1:]]))
