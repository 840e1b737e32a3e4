"""One second-stage file (``refine``) with several trained heads over their shared frozen base: the
heads' softmax weights are averaged, which is the average of their outputs (``RefineConfig.heads``).

    python scripts/refine_ensemble.py runs/refine_ens_c33.safetensors campaigns/c30/refine_c30a \
        campaigns/c33/refine_c33l --preset layer_medium_ctx_x2

Each member is a one-head refine run folder or .safetensors. They must agree on every configuration
field and hold bit-identical bases (the same start file: ``scripts/refine_init.py``), else the script
refuses with one line naming the file. The first member's head keeps the name ``net``; member i + 1's
becomes ``extra_heads.i``. Prints what it wrote; refuses a file that would not load back.

``--widen`` also admits members without the spread features (``RefineConfig.spread``) beside
members with them: their head's first convolution gets zero weights for the spread channels (the
last ones of the features), so it computes what it did, and the ensemble reads the spread
(campaign 36: the shipped x2's heads beside the spread heads of campaign 35).

``--run DIR`` also writes a run folder that ``python -m mcdenoise.models.ship`` reads (the members must
then be run folders): the first member's config.json with the ensemble's preset and model_config and
the list of members, and a result.json whose wall and CPU seconds are the members' sums (the
ensemble itself trains nothing). The card's training command is then the first member's; the true
recipe (every member's command, then this script) goes in its note.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from safetensors.torch import save_file

from average_weights import _weights_file  # scripts/ is on the path when a script runs
from mcdenoise.io.safety import atomic_file
from mcdenoise.models.weights import load_denoiser, model_from_config
from reconfigure_weights import read_weights


def _full(cfg: dict) -> dict:
    """``cfg`` with every field it leaves out at RefineConfig's default (a file saved before a field
    existed, e.g. ``heads``, means the default), as JSON reads it back."""
    from dataclasses import asdict

    from mcdenoise.models.refine_config import RefineConfig

    return json.loads(json.dumps({**asdict(RefineConfig()), **cfg}, default=list))


def _widened(name: str, t: torch.Tensor, want: torch.Size, f: Path) -> torch.Tensor:
    """Head tensor ``t`` of member ``f`` shaped as the ensemble's ``want``: the first convolution of a
    head without the spread features gets zero weights for them (the last N_SPREAD input channels)."""
    from mcdenoise.models.refine import N_SPREAD

    if t.shape == want:
        return t
    if t.dim() == len(want) and t.shape[0] == want[0] and t.shape[2:] == want[2:] and want[1] == t.shape[1] + N_SPREAD:
        return torch.cat([t, t.new_zeros(t.shape[0], N_SPREAD, *t.shape[2:])], dim=1)
    raise ValueError(f"{f}: tensor {name} has shape {tuple(t.shape)}, the ensemble's head needs {tuple(want)}")


def ensemble(members: list[str], preset: str, widen: bool = False) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of the ensemble of ``members`` (ValueError naming the member that differs).
    With ``widen``, members may differ in ``spread`` (module docstring)."""
    if len(members) < 2:
        raise ValueError("an ensemble needs at least two members")
    files = [_weights_file(m) for m in members]
    read = [read_weights(str(f)) for f in files]
    cfgs = [json.loads(meta.get("model_config", "{}")) for meta, _ in read]
    for f, (meta, _), cfg in zip(files, read, cfgs):
        if meta.get("model") != "refine" or int(cfg.get("heads", 1)) != 1:
            raise ValueError(f"{f}: not a one-head refine file")
    spread = any(bool(c.get("spread", False)) for c in cfgs) if widen else bool(cfgs[0].get("spread", False))
    cfg = {**cfgs[0], "heads": len(files), **({"spread": spread} if widen else {})}
    model = model_from_config("refine", preset, cfg)  # the preset and config must build the ensemble
    want = model.state_dict()

    def key(c: dict) -> dict:
        return {**_full(c), "spread": spread} if widen else _full(c)

    ten0 = read[0][1]
    out: dict[str, torch.Tensor] = {}
    for i, (f, (meta, ten), c) in enumerate(zip(files, read, cfgs)):
        if key(c) != key(cfgs[0]):
            raise ValueError(f"{f}: its model or configuration differs from {files[0]}'s")
        if set(ten) != set(ten0):
            raise ValueError(f"{f}: tensor names differ from {files[0]}'s")
        for k, t in ten.items():
            if k.startswith("base."):
                if not torch.equal(t, ten0[k]):
                    raise ValueError(f"{f}: base tensor {k} differs from {files[0]}'s (not the same frozen base)")
                out[k] = t
            elif k.startswith("net."):
                name = k if i == 0 else f"extra_heads.{i - 1}.{k.removeprefix('net.')}"
                out[name] = _widened(k, t, want[name].shape, f)
            else:
                raise ValueError(f"{f}: unexpected tensor {k}")
    model.load_state_dict(out, strict=True)
    meta = {"model": "refine", "preset": preset, "model_config": json.dumps(cfg),
            "ensemble_of": json.dumps([str(f) for f in files])}
    return out, meta


def write_run(run: Path, members: list[str], tensors: dict[str, torch.Tensor], meta: dict[str, str]) -> None:
    """The ensemble as a run folder: model.safetensors, config.json and result.json (module docstring)."""
    dirs = [Path(m) for m in members]
    if not all((d / "config.json").is_file() and (d / "result.json").is_file() for d in dirs):
        raise ValueError("--run needs run folders with config.json and result.json as members")
    docs = [json.loads((d / "config.json").read_text()) for d in dirs]
    results = [json.loads((d / "result.json").read_text()) for d in dirs]
    if any(r.get("wall_s") != r.get("wall_s_this_call") for r in results):
        raise ValueError("a member run was resumed: its CPU seconds are not all in its result.json")
    config = dict(docs[0])
    config["train"] = {**docs[0]["train"], "preset": meta["preset"]}
    config["model_config"] = json.loads(meta["model_config"])
    members_doc = [{"run": str(d), "seed": doc["train"].get("seed"), "data": doc["train"].get("data"),
                    "cpu_s": r.get("cpu_s_this_call"), "wall_s": r.get("wall_s")} for d, doc, r in zip(dirs, docs, results)]
    config["ensemble_of"] = members_doc
    result = {"model": "refine", "preset": meta["preset"], "steps": results[0].get("steps"), "skipped": 0,
              "device": results[0].get("device"), "world_size": 1,
              "wall_s": sum(r["wall_s"] for r in results), "wall_s_this_call": sum(r["wall_s"] for r in results),
              "cpu_s_this_call": sum(r["cpu_s_this_call"] for r in results), "val": None, "ensemble_of": members_doc}
    run.mkdir(parents=True, exist_ok=True)
    with atomic_file(run / "model.safetensors") as tmp:
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp), metadata={**meta, "step": str(result["steps"])})
    for name, doc in (("config.json", config), ("result.json", result)):
        with atomic_file(run / name) as tmp:
            tmp.write_text(json.dumps(doc, indent=1) + "\n")
    load_denoiser(run)  # refuses a folder that would not load back


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dst", type=Path)
    ap.add_argument("members", nargs="+", help="one-head refine run folders or .safetensors files")
    ap.add_argument("--preset", default="layer_medium_ctx_x2")
    ap.add_argument("--run", type=Path, help="also write this run folder for mcdenoise.models.ship")
    ap.add_argument("--widen", action="store_true",
                    help="admit members without the spread features beside members with them")
    a = ap.parse_args()
    try:
        tensors, meta = ensemble(a.members, a.preset, a.widen)
        if a.run is not None:
            write_run(a.run, a.members, tensors, meta)
    except (ValueError, OSError, KeyError) as e:
        sys.exit(f"refine_ensemble: error: {e}")
    with atomic_file(a.dst) as tmp:
        save_file({k: v.contiguous() for k, v in tensors.items()}, str(tmp), metadata=meta)
    load_denoiser(a.dst)  # refuses anything that would not load back
    print(f"wrote {a.dst}: refine ({a.preset}) with {len(a.members)} heads over one frozen base")


if __name__ == "__main__":
    main()
