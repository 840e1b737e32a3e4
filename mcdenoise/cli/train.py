"""Train a denoiser on a dataset folder into a run folder.

    mcdenoise train --model NAME [--preset small] --data DATASET_DIR --out RUN_DIR [--steps N]
                    [--batch B] [--crop C] [--lr LR] [--loss NAME] [--device cpu|cuda|auto]
                    [--resume] [--force] [--seed S] [--val-every K] [--checkpoint-every K]
                    [--workers W] [--target reference|noisy] [--sampling importance|uniform]
    mcdenoise train --out RUN_DIR --resume          # continue a run with its saved settings
    torchrun --nproc_per_node 2 -m mcdenoise.cli.main train ...   # several processes

See docs/TRAINING.md for the run folder's contents.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

#: CLI flag (dest) -> TrainConfig field, for the flags that map one to one.
_FIELDS = ("model", "preset", "init", "data", "val_data", "min_lr_fraction", "steps", "batch", "crop", "lr", "loss", "device", "seed", "val_every",
           "checkpoint_every", "keep_every", "workers", "threads", "target", "sampling", "warmup", "schedule", "clip_grad",
           "branch_fraction", "amp", "val_images")


def add_parser(p: argparse.ArgumentParser) -> None:
    # No torch import here: every `mcdenoise` command builds this parser (--version stays fast).
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = __doc__.split("\n\n", 1)[1]
    p.add_argument("--model", help="registered model name (see `mcdenoise models`)")
    p.add_argument("--preset", help="model preset (default small)")
    p.add_argument("--init", help="start from these weights (fine-tune): a shipped model name, run folder or .safetensors")
    p.add_argument("--data", help="dataset folder from `mcdenoise dataset`; several separated by commas train on their union")
    p.add_argument("--val-data", help="validate on this dataset's val split (e.g. one with references; default --data)")
    p.add_argument("--out", type=Path, required=True, help="run folder (created; see --resume and --force)")
    p.add_argument("--steps", type=int, help="optimizer steps (default 2000); with --resume, more steps extend a finished run")
    p.add_argument("--batch", type=int, help="global batch, crops per step over all processes (default 8)")
    p.add_argument("--crop", type=int, help="crop edge in pixels (default 48)")
    p.add_argument("--lr", type=float, help="peak learning rate (default: the model's, see docs/TRAINING.md)")
    p.add_argument("--loss", help="l1, l2, relmse, relmse_ref, relmse_in, relmse_in_wide, smape, tonemapped_l2, log_l1 or lowpass_l1 (default: the model's paper's); "
                   "or a weighted sum such as smape+0.1*relmse_ref")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), help="default auto: CUDA when available")
    p.add_argument("--seed", type=int, help="seeds the weights and every batch (default 0)")
    p.add_argument("--val-every", type=int, help="validate every K steps and at the end (default 200; 0 = end only)")
    p.add_argument("--val-images", type=int, help="at most this many validation images (default 8)")
    p.add_argument("--checkpoint-every", type=int, help="checkpoint every K steps and at the end (default 100)")
    p.add_argument("--keep-every", type=int, help="keep the checkpoints at multiples of K steps (default 1000)")
    p.add_argument("--workers", type=int, help="data-loader processes per training process (default 2)")
    p.add_argument("--threads", type=int, help="torch threads per training process (default: torch's; 1 helps on 2 cores)")
    p.add_argument("--target", choices=("reference", "noisy"), help="reference (default) or noisy (Noise2Noise)")
    p.add_argument("--sampling", choices=("importance", "uniform"), help="crop placement (default importance)")
    p.add_argument("--spp", type=int, nargs=2, metavar=("LO", "HI"), help="random input spp range (default 2 8 for sample models)")
    p.add_argument("--no-augment", action="store_true", help="no flips or rotations")
    p.add_argument("--exposure", type=float, nargs=2, metavar=("LO", "HI"),
                   help="exposure augmentation: each crop times a factor log-uniform in LO..HI (default off)")
    p.add_argument("--warmup", type=float, help="fraction of steps with linear warm-up (default 0.02)")
    p.add_argument("--schedule", choices=("cosine", "step", "constant"), help="decay after warm-up (default cosine)")
    p.add_argument("--clip-grad", type=float, help="clip the gradient norm (default 1.0; 0 = off)")
    p.add_argument("--min-lr-fraction", type=float, help="final learning rate of the cosine schedule, a fraction of the peak (default 0.05)")
    p.add_argument("--model-overrides", type=_json_object, metavar="JSON",
                   help='fields of the preset\'s model configuration to replace, e.g. \'{"layers": 4}\' (ablations)')
    p.add_argument("--branch-fraction", type=float, help="KPCN/DPCN: fraction of steps on per-branch losses (default 0.8)")
    p.add_argument("--amp", choices=("none", "bf16"),
                   help="bf16 autocast of the forward pass, on CUDA or a CPU with AVX512-BF16/AMX (default none)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its newest checkpoint")
    p.add_argument("--force", action="store_true", help="replace an existing run in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _json_object(text: str) -> dict:
    import json

    try:
        v = json.loads(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"not JSON ({e})") from None
    if not isinstance(v, dict):
        raise argparse.ArgumentTypeError("expected a JSON object, e.g. '{\"layers\": 4}'")
    return v


def config_from_args(args: argparse.Namespace):  # -> TrainConfig
    """Build the TrainConfig; with ``--resume`` and no ``--model``, start from the run's saved one."""
    from mcdenoise.train.config import ConfigError, TrainConfig, read_config
    from mcdenoise.io.run_folder import CONFIG_FILE

    given = {f: getattr(args, f) for f in _FIELDS if getattr(args, f) is not None}
    if args.model_overrides is not None:
        given["model_overrides"] = args.model_overrides
    if args.spp is not None:
        given["spp_range"] = tuple(args.spp)
    if args.exposure is not None:
        given["exposure"] = tuple(args.exposure)
    if args.no_augment:
        given["augment"] = False
    if args.no_progress:
        given["progress"] = False
    if args.model is None:
        if not args.resume:
            raise ConfigError("--model is required (or --resume with an existing --out)")
        path = args.out / CONFIG_FILE
        if not path.is_file():
            raise ConfigError(f"{args.out}: nothing to resume (no {CONFIG_FILE}); give --model and --data to start a run")
        base = TrainConfig.from_json(read_config(path)["train"])
        return dataclasses.replace(base, **given)
    if "data" not in given:
        raise ConfigError("--data is required")
    return TrainConfig(**given)


def run(args: argparse.Namespace) -> int:
    from mcdenoise.train.loop import train

    cfg = config_from_args(args)
    res = train(cfg, args.out, resume=args.resume, force=args.force)
    if res.val:
        shown = ", ".join(f"{k} {v:.4g}" for k, v in res.val.items())
        print(f"{res.run_dir}: {res.step} steps, {res.skipped} skipped, validation: {shown}", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    from mcdenoise.cli.main import main

    sys.exit(main(["train", *sys.argv[1:]]))
