"""Average the weights of runs that share an architecture (a "model soup"; Wortsman et al. 2022,
"Robust fine-tuning of zero-shot models", WiSE-FT): ``sum_i w_i * theta_i``, written as a new
weights file with the first file's metadata (model, preset, model_config) and ``step`` removed.

The runs should descend from one start (a fine-tune and the weights it began from): averaging
unrelated runs gives a model that matches neither. Campaign 16 used it to put a GPU fine-tune on
fresh images between the shipped layer-medium and itself, choosing the mix on our own held-out
images (scripts/consistency_probe.py), never on the third-party scenes.

    python scripts/average_weights.py runs/soup.safetensors \
        mcdenoise/models/shipped/layer-medium.safetensors runs/c16_2/lm16a --weights 0.5 0.5 \
        --set consistency=4
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from mcdenoise.io.safety import atomic_file
from mcdenoise.models.weights import model_from_config
from reconfigure_weights import apply_sets  # scripts/ is on the path when run as a script


def _weights_file(path: str) -> Path:
    """A .safetensors file, or a run folder's model.safetensors."""
    p = Path(path)
    return p / "model.safetensors" if p.is_dir() else p


def average(files: list[Path], weights: list[float]) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """The weighted sum of the tensors of ``files`` (same names and shapes, else ValueError), and
    the first file's metadata."""
    total: dict[str, torch.Tensor] = {}
    meta: dict[str, str] = {}
    for i, (f, w) in enumerate(zip(files, weights)):
        with safe_open(str(f), "pt") as h:
            if i == 0:
                meta = dict(h.metadata() or {})
            names = set(h.keys())
            if i and names != set(total):
                raise ValueError(f"{f}: tensor names differ from {files[0]}")
            for k in names:
                t = h.get_tensor(k)
                if i and t.shape != total[k].shape:
                    raise ValueError(f"{f}: {k} has shape {tuple(t.shape)}, {files[0]} has {tuple(total[k].shape)}")
                if not t.is_floating_point():  # counters (e.g. batch-norm steps) are not averaged
                    total.setdefault(k, t)
                    continue
                acc = t.double() * w
                total[k] = acc if i == 0 else total[k] + acc
    return {k: (v.float() if v.is_floating_point() else v) for k, v in total.items()}, meta


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", help="the averaged .safetensors to write")
    ap.add_argument("inputs", nargs="+", help=".safetensors files or run folders")
    ap.add_argument("--weights", nargs="+", type=float, help="one per input, summing to 1 (default: equal)")
    ap.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                    help="model configuration fields to replace in the output (as scripts/reconfigure_weights.py)")
    a = ap.parse_args()
    weights = a.weights or [1.0 / len(a.inputs)] * len(a.inputs)
    if len(weights) != len(a.inputs) or abs(sum(weights) - 1.0) > 1e-6:
        ap.error("--weights: one per input, summing to 1")
    try:
        tensors, meta = average([_weights_file(p) for p in a.inputs], weights)
    except (ValueError, OSError) as e:  # one line naming the file and the problem
        raise SystemExit(f"average_weights: {e}") from None
    if "model_config" not in meta:
        ap.error(f"{a.inputs[0]}: no model_config in its metadata (use a shipped file or a recent run)")
    cfg = json.loads(meta["model_config"])
    apply_sets(cfg, a.set)
    model = model_from_config(meta["model"], meta["preset"], cfg)  # the result must build and load strictly
    model.load_state_dict(tensors, strict=True)
    meta = {k: v for k, v in meta.items() if k != "step"}
    meta["model_config"] = json.dumps(cfg)
    meta["averaged_from"] = json.dumps({p: w for p, w in zip(a.inputs, weights)})
    with atomic_file(a.out) as tmp:  # a reader never sees half a file
        save_file(tensors, str(tmp), metadata=meta)
    print(f"wrote {a.out}: {' + '.join(f'{w:g} x {p}' for p, w in zip(a.inputs, weights))}")


if __name__ == "__main__":
    main()
