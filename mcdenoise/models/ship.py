"""Ship a trained run's weights inside the package, with a model card.

    python -m mcdenoise.models.ship RUN_DIR [--eval REPORT_DIR/results.json] [--force]

writes ``mcdenoise/models/shipped/<name>-<preset>.safetensors`` (the run's final weights, with
``model``, ``preset`` and ``model_config`` in the safetensors metadata, so the file alone rebuilds
the model) and ``<name>-<preset>.json``, the model card: the commands that reproduce the weights
from scratch (dataset and training, rebuilt from the run's ``config.json`` and the dataset's
``dataset.json``, so they are the settings that actually ran), steps, wall time, device, the last
validation figures, and -- from an ``mcdenoise eval`` results file -- the metrics on the held-out
test split with Open Image Denoise on the same images.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import json
import platform
import shlex
import sys
from pathlib import Path
from typing import Any

from mcdenoise.errors import McDenoiseError
from mcdenoise.io.atomic import atomic_file
from mcdenoise.io.run_folder import CONFIG_FILE, RESULT_FILE, WEIGHTS_FILE, checkpoint_run
from mcdenoise.models.weights import SHIPPED_DIR, WeightsError, load_denoiser, preset_differences

__all__ = ["dataset_command", "train_command", "model_card", "card_markdown", "ship"]


def _datasets_command(spec: str) -> str | None:
    """The commands that render every procedural dataset of a ``--data`` value again (several are
    separated by commas), joined by `` && ``; None when none of them was made by ``mcdenoise dataset``."""
    from mcdenoise.data.dataset import dataset_dirs

    cmds = [dataset_command(d) for d in dataset_dirs(spec) if (d / "dataset.json").is_file()]
    return " && ".join(cmds) or None


def dataset_command(data_dir: str | Path) -> str:
    """The ``mcdenoise dataset`` command that renders ``data_dir`` again, from its dataset.json.

    It states the Mitsuba variant (a GPU host's ``auto`` renders other pixels than the CPU's):
    dataset.json's, else, for datasets made before it was recorded there, the one the images'
    meta.json name."""
    from mcdenoise.render.procedural_dataset import images_variant

    p = Path(data_dir) / "dataset.json"
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError) as e:
        raise WeightsError(f"{p}: cannot read the dataset's settings ({e})") from None
    from mcdenoise.render.cycles.dataset import CONFIG_FORMAT as CYCLES_FORMAT, recipe_command

    if d.get("format") == CYCLES_FORMAT:
        return recipe_command(data_dir, d)
    size = d["width"] if d["width"] == d["height"] else f"{d['width']}x{d['height']}"
    args = ["mcdenoise", "dataset", "--out", str(data_dir), "--count", str(d["count"]), "--spp", str(d["spp"]),
            "--ref-spp", str(d["ref_spp"]), "--size", str(size), "--seed", str(d["seed"])]
    variant = d.get("variant") or images_variant(data_dir)
    if variant is None:
        raise WeightsError(f"{p}: records no Mitsuba variant and no image names one: the dataset command "
                           "cannot be stated")
    args += ["--variant", variant]
    # Always named: the default moves when a new scene pipeline lands, and the recipe must not.
    args += ["--generator", str(d.get("generator", 1))]
    if d.get("views", 1) != 1:
        args += ["--views", str(d["views"])]
    if d.get("frames", 1) != 1:
        args += ["--frames", str(d["frames"])]
    if d.get("kind"):
        args += ["--kind", d["kind"]]
    if d.get("max_depth", 6) != 6:
        args += ["--max-depth", str(d["max_depth"])]
    if d.get("rr_depth", 5) != 5:
        args += ["--rr-depth", str(d["rr_depth"])]
    if d.get("world", "classic") != "classic":
        args += ["--world", d["world"]]
    if d.get("small_emitters") is not None:
        args += ["--small-emitters", f"{d['small_emitters']:g}"]
    if d.get("strong_dof") is not None:
        args += ["--strong-dof", f"{d['strong_dof']:g}"]
    lo, hi = d.get("objects", [10, 50])
    if [lo, hi] != [10, 50]:
        args += ["--objects", f"{lo}-{hi}"]
    args += ["--split", ",".join(f"{x:g}" for x in d["fractions"])]
    return shlex.join(args)


#: TrainConfig field -> CLI flag, for the fields a command must spell out when not at the default.
def _flags() -> dict[str, str]:
    """TrainConfig field -> its ``mcdenoise train`` flag, read from the command's own parser (a
    hand-kept table went stale: fields without a flag made cards state a wrong command)."""
    import argparse

    from mcdenoise.cli.train import add_parser

    p = argparse.ArgumentParser()
    add_parser(p)
    skip = {"model", "data", "out", "spp", "resume", "force", "no_progress", "no_augment", "device"}
    return {a.dest: a.option_strings[-1] for a in p._actions if a.option_strings and a.dest not in skip}


def train_command(config_doc: dict[str, Any], out: str | Path) -> str:
    """The ``mcdenoise train`` command with every setting of a run's config.json that differs from the defaults."""
    from mcdenoise.train.config import TrainConfig

    t = config_doc["train"]
    default = TrainConfig().to_json()
    flags = _flags()
    args = ["mcdenoise", "train", "--model", t["model"], "--data", t["data"], "--out", str(out)]
    for field, value in t.items():
        if field not in flags or value is None or value == default.get(field):
            continue
        if isinstance(value, dict):
            value = json.dumps(value, sort_keys=True)
        args += [flags[field], f"{value:g}" if isinstance(value, float) else str(value)]
    unstated = sorted(f for f, v in t.items() if f not in flags and v != default.get(f)
                      and f not in ("model", "data", "spp_range", "augment", "progress", "device"))
    if unstated:
        raise WeightsError(f"the run's settings {unstated} have no `mcdenoise train` flag: its command cannot be stated")
    if t.get("spp_range") and t.get("spp_range") != default.get("spp_range"):
        args += ["--spp", *map(str, t["spp_range"])]
    if not t.get("augment", True):
        args.append("--no-augment")
    return shlex.join(args)


def _test_metrics(results: dict[str, Any], weights: str) -> dict[str, Any]:
    """This model's mean metrics per spp, and the baselines' on the same images, from eval's results.json.

    The model is the method whose weights file is ``weights``; baselines are every non-model
    method (noisy input, OIDN qualities, the classic filter). Subsets (e.g. depth of field and
    motion blur) are kept under their names.
    """
    methods = results.get("methods", [])
    target = Path(weights).resolve()
    mine = [m["name"] for m in methods if m.get("kind") == "model" and m.get("weights") and Path(m["weights"]).resolve() == target]
    if not mine:
        raise WeightsError(f"eval results do not include these weights ({weights}); evaluate the run folder first")
    baselines = {m["name"] for m in methods if m.get("kind") != "model"}
    out: dict[str, Any] = {"data": results.get("config", {}).get("data"), "split": results.get("config", {}).get("split"),
                           "images": len(results.get("images", [])), "oidn_version": results.get("provenance", {}).get("oidn"),
                           "command": results.get("command"), "subsets": {}}
    for row in results.get("summary", []):
        name = "model" if row["method"] == mine[0] else row["method"] if row["method"] in baselines else None
        if name is None:
            continue
        metrics = {k: v for k, v in row.items() if k not in ("subset", "method", "spp")}
        out["subsets"].setdefault(row["subset"], {}).setdefault(str(row["spp"]), {})[name] = metrics
    return out


def validation_metrics(results: dict[str, Any], weights: str) -> dict[str, Any]:
    """The card's ``validation`` block from an ``mcdenoise eval --scenes`` results.json: mean
    metrics per spp of this model, the noisy input and OIDN (``spp``), and relMSE per scene
    (``scenes``), which :mod:`mcdenoise.infer.choose` ranks models by (issue 20)."""
    t = _test_metrics(results, weights)
    per_spp = (t.get("subsets") or {}).get("all") or next(iter((t.get("subsets") or {}).values()), {})
    target = Path(weights).resolve()
    mine = {m["name"] for m in results.get("methods", []) if m.get("kind") == "model" and m.get("weights")
            and Path(m["weights"]).resolve() == target}
    scenes: dict[str, dict[str, dict[str, float]]] = {}
    for r in results.get("rows", []):
        name = "model" if r["method"] in mine else r["method"] if r["method"] in ("noisy", "oidn-high", "oidn-fast") else None
        if name is not None and isinstance(r.get("relmse"), (int, float)):
            scene = Path(str(r["image"])).name.split("_")[0]
            scenes.setdefault(scene, {}).setdefault(str(r["spp"]), {})[name] = float(r["relmse"])
    return {"data": t.get("data"), "command": t.get("command"), "oidn_version": t.get("oidn_version"),
            "images": t.get("images"), "spp": per_spp, "scenes": scenes}


def annotate(stem: str, valscenes_json: str | Path, *, out_dir: Path = SHIPPED_DIR) -> Path:
    """Add (or replace) the ``validation`` block of the shipped card ``<stem>.json``; the weights
    are not touched (their SHA-256 must still match the card)."""
    c_path, w_path = out_dir / f"{stem}.json", out_dir / f"{stem}.safetensors"
    try:
        card = json.loads(c_path.read_text())
        results = json.loads(Path(valscenes_json).read_text())
    except (OSError, ValueError) as e:
        raise WeightsError(f"annotate {stem}: cannot read the card or the results ({e})") from None
    if card.get("weights_sha256") != hashlib.sha256(w_path.read_bytes()).hexdigest():
        raise WeightsError(f"{w_path}: does not match its card's weights_sha256")
    card["validation"] = validation_metrics(results, str(w_path))
    with atomic_file(c_path) as tmp:
        tmp.write_text(json.dumps(card, indent=1) + "\n")
    return c_path


def model_card(run_dir: Path, model: Any, info: dict[str, Any], results: dict[str, Any] | None) -> dict[str, Any]:
    from mcdenoise.train.config import read_config

    doc = read_config(run_dir / CONFIG_FILE)
    res = json.loads((run_dir / RESULT_FILE).read_text()) if (run_dir / RESULT_FILE).is_file() else {}
    t = doc["train"]
    card: dict[str, Any] = {
        "format": "mcdenoise-model-card",
        "version": 1,
        "name": info["name"],
        "preset": info["preset"],
        "model_config": doc.get("model_config"),
        "inputs": list(model.required_channels()),
        "input_kind": model.input_kind,
        "parameters": sum(p.numel() for p in model.parameters()),
        "dataset": {"command": _datasets_command(t["data"]),
                    "path": t["data"], "manifest_sha256": doc.get("manifest_sha256")},
        "training": {
            "command": train_command(doc, f"runs/{info['name']}"),
            "steps": res.get("steps", t["steps"]),
            "wall_s": res.get("wall_s"),
            "cpu_s": res.get("cpu_s_this_call") if res.get("wall_s") == res.get("wall_s_this_call") else None,
            "device": res.get("device"),
            "threads": t.get("threads"),
            "world_size": doc.get("world_size"),
            "torch_version": doc.get("torch_version"),
            "mcdenoise_version": doc.get("mcdenoise_version"),
            "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            "final_validation": res.get("val"),
        },
        "shipped": datetime.date.today().isoformat(),
    }
    if results is not None:
        card["test"] = _test_metrics(results, info["weights"])
    return card


def card_markdown(card: dict[str, Any]) -> str:
    """The card as the Markdown block that docs/TRAINING.md shows for one shipped model."""
    t = card["training"]
    wall = f"{t['wall_s'] / 60:.0f} min wall" if t.get("wall_s") else "? wall"
    if t.get("cpu_s"):
        wall += f" ({t['cpu_s'] / 60:.0f} CPU-min, loader workers included)"
    lines = [f"**{card['name']}** (`{card['preset']}` preset, {card['parameters']:,} parameters, inputs: "
             f"{', '.join(card['inputs'])}): {t['steps']} steps, {wall} on {t.get('device')} "
             f"({t.get('threads') or 'default'} thread(s), {t.get('machine')}"
             + ("; the machine was shared, so wall time overstates the compute" if str(t.get("device", "cpu")).startswith("cpu") else "")
             + ").", "", "```"]
    if card["dataset"].get("command"):
        lines.append(card["dataset"]["command"])
    src = f"runs/{card['name']}" + (f"/checkpoints/step_{t['checkpoint']:08d}" if t.get("checkpoint") else "")
    test = card.get("test") or {}
    lines.append(t["command"].split("  # ")[0])
    report = "REPORT"
    if test.get("command"):
        lines.append(test["command"])
        argv = shlex.split(test["command"])
        report = argv[argv.index("--out") + 1] if "--out" in argv else report
    preset = f" --preset {card['preset']}" if t.get("preset_note") else ""
    lines += [f"python -m mcdenoise.models.ship {src}{preset} --eval {report}/results.json --force", "```"]
    if t.get("note"):
        lines += ["", f"Shipped: the {t['note']}."]
    if t.get("preset_note"):
        lines += ["", f"Preset: {t['preset_note']}."]
    data = ", ".join(test.get("data") or []) if isinstance(test.get("data"), list) else test.get("data")
    for subset, per_spp in (test.get("subsets") or {}).items():
        rows = sorted(per_spp.items(), key=lambda kv: int(kv[0]))
        lines += ["", f"Test relMSE ({subset} images of {data}, {test.get('split')} split; "
                      f"OIDN {test.get('oidn_version')} on the same images):", "",
                  "| spp | noisy | this model | improvement | OIDN high | OIDN fast |", "|---|---|---|---|---|---|"]
        for spp, r in rows:
            def f(k: str) -> float | None:
                v = (r.get(k) or {}).get("relmse")
                return float(v) if isinstance(v, (int, float)) else None

            def s(v: float | None) -> str:
                return f"{v:.4f}" if v is not None else "-"
            n, m = f("noisy"), f("model")
            gain = f"{n / m:.1f}x" if n and m else "-"
            lines.append(f"| {spp} | {s(n)} | {s(m)} | {gain} | {s(f('oidn-high'))} | {s(f('oidn-fast'))} |")
    return "\n".join(lines)


def _check_preset(name: str, preset: str, run_config: dict[str, Any] | None, run: Path) -> None:
    """Refuse (one line) to record ``preset`` for a run whose architecture differs from it."""
    diff = preset_differences(name, preset, run_config)
    if diff:
        raise WeightsError(f"{run}: its model configuration differs from preset {preset!r} of {name!r} in {', '.join(diff[:4])}")


def ship(run_dir: str | Path, *, results_json: str | Path | None = None, out_dir: Path = SHIPPED_DIR,
         force: bool = False, docs: str | Path | None = None, cpu_seconds: float | None = None,
         preset: str | None = None) -> tuple[Path, Path]:
    """Copy ``run_dir``'s final weights into ``out_dir`` with a model card. Returns (weights, card).

    With ``docs`` (e.g. docs/TRAINING.md), the card's commands and test figures also go into the
    generated block ``shipped:<name>-<preset>`` of that file. ``preset`` records the weights under
    another preset than the run's, for a run trained with ``--model-overrides`` that equal it (the
    card's training command stays the run's own).
    """
    from safetensors.torch import save_file

    from mcdenoise.train.checkpoint import state_dict_for_safetensors

    run = Path(run_dir)
    if not (run / WEIGHTS_FILE).is_file():
        raise WeightsError(f"{run}: no final {WEIGHTS_FILE} (is the run finished?)")
    model, info = load_denoiser(run)
    checkpoint = None
    owner = checkpoint_run(run)
    if owner is not None:  # a checkpoint folder RUN/checkpoints/step_N (early stopping)
        checkpoint, run = run, owner
    results = None
    if results_json is not None:
        try:
            results = json.loads(Path(results_json).read_text())
        except (OSError, ValueError) as e:
            raise WeightsError(f"{results_json}: cannot read eval results ({e})") from None
    if preset is not None and preset != info["preset"]:
        _check_preset(info["name"], preset, dataclasses.asdict(model.config), run)
        trained_as = info["preset"]
        info = {**info, "preset": preset}
    else:
        trained_as = None
    card = model_card(run, model, info, results)
    if trained_as is not None:
        card["training"]["preset_note"] = (f"trained as preset {trained_as!r} with --model-overrides that equal preset "
                                           f"{preset!r} (which was added after the run)")
    if checkpoint is not None:
        card["training"]["checkpoint"] = info["step"]
        card["training"]["note"] = (f"weights of step {info['step']} of the {card['training']['steps']}-step run "
                                    f"({checkpoint.relative_to(run)}), chosen by its validation loss")
        card["training"]["command"] += f"  # then ship runs/{info['name']}/{checkpoint.relative_to(run).as_posix()}"
    if cpu_seconds is not None:  # measured outside the run (runs older than result.json's cpu_s field)
        card["training"]["cpu_s"] = float(cpu_seconds)
    stem = f"{info['name']}-{info['preset']}"
    w_path, c_path = out_dir / f"{stem}.safetensors", out_dir / f"{stem}.json"
    if w_path.exists() and not force:
        raise WeightsError(f"{w_path}: shipped weights exist; pass --force to replace them")
    out_dir.mkdir(parents=True, exist_ok=True)
    if c_path.is_file():  # a re-ship keeps what was measured about the input sources (choose.py's not_for)
        try:
            old = json.loads(c_path.read_text())
        except ValueError:
            old = {}
        if old.get("not_for"):
            card["not_for"] = old["not_for"]
    meta = {"model": info["name"], "preset": info["preset"], "model_config": json.dumps(card["model_config"]),
            "step": str(card["training"]["steps"])}
    with atomic_file(w_path) as tmp:
        save_file(state_dict_for_safetensors(model), str(tmp), metadata=meta)
    card["weights_sha256"] = hashlib.sha256(w_path.read_bytes()).hexdigest()
    with atomic_file(c_path) as tmp:
        tmp.write_text(json.dumps(card, indent=1) + "\n")
    if docs is not None:
        from mcdenoise.eval.docblock import replace_block

        replace_block(docs, f"shipped:{stem}", card_markdown(card), heading=f"### {stem}")
    return w_path, c_path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m mcdenoise.models.ship", description=__doc__.strip().splitlines()[0])
    p.add_argument("run", type=Path, nargs="?", help="finished run folder of `mcdenoise train`")
    p.add_argument("--annotate", metavar="NAME-PRESET", help="only add --valscenes results to this shipped card")
    p.add_argument("--valscenes", type=Path, help="results.json of `mcdenoise eval --scenes` that includes these weights")
    p.add_argument("--eval", type=Path, help="results.json of `mcdenoise eval` that includes this run")
    p.add_argument("--force", action="store_true", help="replace shipped weights of the same name and preset")
    p.add_argument("--docs", type=Path, default=Path("docs/TRAINING.md"),
                   help="Markdown file whose block shipped:<name>-<preset> gets the card (default docs/TRAINING.md)")
    p.add_argument("--cpu-seconds", type=float, help="CPU seconds the run took, when its result.json lacks them")
    p.add_argument("--preset", help="record this preset instead of the run's (the run's --model-overrides must equal it)")
    a = p.parse_args(argv)
    try:
        if a.annotate:
            if a.valscenes is None:
                raise WeightsError("--annotate needs --valscenes REPORT/results.json")
            print(f"wrote {annotate(a.annotate, a.valscenes)}")
            return 0
        if a.run is None:
            raise WeightsError("give a run folder (or --annotate NAME-PRESET --valscenes ...)")
        w, c = ship(a.run, results_json=a.eval, force=a.force, docs=a.docs, cpu_seconds=a.cpu_seconds, preset=a.preset)
        if a.valscenes is not None:
            annotate(w.stem, a.valscenes, out_dir=w.parent)
    except McDenoiseError as e:
        print(f"ship: error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {w} ({w.stat().st_size / 1e6:.2f} MB) and {c}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
