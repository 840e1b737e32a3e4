"""One second-stage file (``refine``) with several trained heads over their shared frozen base: the
heads' softmax weights are averaged, which is the average of their outputs (``RefineConfig.heads``).

    python scripts/refine_ensemble.py runs/refine_ens_c33.safetensors campaigns/c30/refine_c30a \
        campaigns/c33/refine_c33l --preset layer_medium_ctx_x2

Each member is a one-head refine run folder or .safetensors. They must agree on every configuration
field and hold bit-identical bases (the same start file: ``scripts/refine_init.py``), else the script
refuses with one line naming the file. The first member's head keeps the name ``net``; member i + 1's
becomes ``extra_heads.i``. Prints what it wrote; refuses a file that would not load back.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from mcdenoise.io.safety import atomic_file
from mcdenoise.models.weights import load_denoiser, model_from_config


def _weights_file(path: str) -> Path:
    """A .safetensors file, or a run folder's model.safetensors."""
    p = Path(path)
    return p / "model.safetensors" if p.is_dir() else p


def _read(path: Path) -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    with safe_open(str(path), "pt") as f:
        return dict(f.metadata() or {}), {k: f.get_tensor(k) for k in f.keys()}


def ensemble(members: list[str], preset: str) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of the ensemble of ``members`` (ValueError naming the member that differs)."""
    if len(members) < 2:
        raise ValueError("an ensemble needs at least two members")
    files = [_weights_file(m) for m in members]
    meta0, ten0 = _read(files[0])
    cfg0 = json.loads(meta0.get("model_config", "{}"))
    if meta0.get("model") != "refine" or int(cfg0.get("heads", 1)) != 1:
        raise ValueError(f"{files[0]}: not a one-head refine file")
    out = dict(ten0)
    for i, f in enumerate(files[1:]):
        meta, ten = _read(f)
        cfg = json.loads(meta.get("model_config", "{}"))
        if meta.get("model") != "refine" or cfg != cfg0:
            raise ValueError(f"{f}: its model or configuration differs from {files[0]}'s")
        if set(ten) != set(ten0):
            raise ValueError(f"{f}: tensor names differ from {files[0]}'s")
        for k, t in ten.items():
            if k.startswith("base."):
                if not torch.equal(t, ten0[k]):
                    raise ValueError(f"{f}: base tensor {k} differs from {files[0]}'s (not the same frozen base)")
            elif k.startswith("net."):
                out[f"extra_heads.{i}.{k.removeprefix('net.')}"] = t
            else:
                raise ValueError(f"{f}: unexpected tensor {k}")
    cfg = {**cfg0, "heads": len(files)}
    model = model_from_config("refine", preset, cfg)  # the preset and config must build the ensemble
    model.load_state_dict(out, strict=True)
    meta = {"model": "refine", "preset": preset, "model_config": json.dumps(cfg),
            "ensemble_of": json.dumps([str(f) for f in files])}
    return out, meta


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dst", type=Path)
    ap.add_argument("members", nargs="+", help="one-head refine run folders or .safetensors files")
    ap.add_argument("--preset", default="layer_medium_ctx_x2")
    a = ap.parse_args()
    try:
        tensors, meta = ensemble(a.members, a.preset)
    except (ValueError, OSError, KeyError) as e:
        sys.exit(f"refine_ensemble: error: {e}")
    with atomic_file(a.dst) as tmp:
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp), metadata=meta)
    load_denoiser(a.dst)  # refuses anything that would not load back
    print(f"wrote {a.dst}: refine ({a.preset}) with {len(a.members)} heads over one frozen base")


if __name__ == "__main__":
    main()
