"""Copy a weights file with fields of its model configuration replaced (the tensors untouched):
the start of a fine-tune into a preset whose layers match but whose inputs or rules differ.

    python scripts/reconfigure_weights.py mcdenoise/models/shipped/kpcn-small.safetensors \
        runs/kpcn_pixel_init.safetensors --preset pixel --set feature_hit=first variance=window variance_window=5

    python scripts/reconfigure_weights.py mcdenoise/models/shipped/sbmc-small.safetensors \
        mcdenoise/models/shipped/sbmc-small.safetensors --keep-step --set consistency=2

    python scripts/reconfigure_weights.py mcdenoise/models/shipped/combine-ens_kpcn.safetensors \
        runs/combine_em_init.safetensors --zero-new-inputs --set emitter_feature=true

Values are read as JSON where they parse (5, 0.25, true), else as strings. The result must still
build: the model is constructed from the new configuration and loads the tensors strictly. With
``--zero-new-inputs`` a field that adds input channels is allowed: a tensor that the new model
has wider in dimension 1 only (a first convolution's inputs) gets zeros for the new channels,
appended last, so the model computes what it did until training moves them.
"""
from __future__ import annotations

import argparse
import json

from safetensors import safe_open
from safetensors.torch import save_file

from mcdenoise.models.weights import model_from_config


def read_weights(spec: str) -> tuple[dict[str, str], dict]:
    """``(metadata, tensors)`` of a shipped model name (``layer-medium``) or a .safetensors file."""
    from mcdenoise.models.weights import shipped_name, shipped_weights

    named = shipped_name(spec)
    path = str(shipped_weights(*named).weights) if named else spec
    with safe_open(path, "pt") as f:
        return dict(f.metadata() or {}), {k: f.get_tensor(k) for k in f.keys()}


def apply_sets(cfg: dict, items: list[str]) -> dict:
    """``cfg`` with each ``FIELD=VALUE`` of ``items`` set (VALUE as JSON where it parses, else a string)."""
    for item in items:
        key, _, raw = item.partition("=")
        try:
            cfg[key] = json.loads(raw)
        except ValueError:
            cfg[key] = raw
    return cfg


def zero_new_inputs(tensors: dict, shapes: dict) -> dict:
    """``tensors`` with each one that ``shapes`` (name -> new shape) has wider in dimension 1 only
    padded with zeros at the end of that dimension; others as they are. Raises on any other change."""
    import torch

    out = {}
    for k, t in tensors.items():
        new = shapes.get(k)
        if new is None or tuple(new) == tuple(t.shape):
            out[k] = t
            continue
        if len(new) < 2 or new[0] != t.shape[0] or tuple(new[2:]) != tuple(t.shape[2:]) or new[1] < t.shape[1]:
            raise SystemExit(f"{k}: shape {tuple(t.shape)} -> {tuple(new)} is not new input channels")
        pad = torch.zeros((t.shape[0], new[1] - t.shape[1], *t.shape[2:]), dtype=t.dtype)
        out[k] = torch.cat([t, pad], dim=1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("src")
    ap.add_argument("dst")
    ap.add_argument("--preset", help="preset name to record (default: the source's)")
    ap.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--keep-step", action="store_true",
                    help="keep the source's training step (a rule set after training on shipped weights); default 0, a new start")
    ap.add_argument("--zero-new-inputs", action="store_true",
                    help="allow fields that add input channels: their weights start at zero (same outputs)")
    a = ap.parse_args()
    with safe_open(a.src, "pt") as f:
        meta = dict(f.metadata() or {})
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    if "model_config" not in meta:  # a run's model.safetensors: its configuration is the run's config.json
        from pathlib import Path

        run = json.loads((Path(a.src).parent / "config.json").read_text())
        meta.update(model=run["train"]["model"], preset=run["train"]["preset"], model_config=json.dumps(run["model_config"]))
    cfg = apply_sets(json.loads(meta["model_config"]), a.set)
    meta.update(model_config=json.dumps(cfg), preset=a.preset or meta.get("preset", ""))
    if not a.keep_step:
        meta["step"] = "0"
    model = model_from_config(meta["model"], meta["preset"], cfg)  # refuses unknown fields
    if a.zero_new_inputs:
        tensors = zero_new_inputs(tensors, {k: tuple(v.shape) for k, v in model.state_dict().items()})
    model.load_state_dict(tensors, strict=True)
    save_file(tensors, a.dst, metadata=meta)
    print(f"wrote {a.dst}: {meta['model']} ({meta['preset']}) with {json.dumps(cfg)}")


if __name__ == "__main__":
    main()
