"""Find and load trained weights: shipped with the package, from a run folder, or from a file.

One resolver, :func:`load_denoiser`, turns what a user types into a ready model:

* a registered name (``"wskp"``): the weights shipped in ``mcdenoise/models/shipped/`` for that
  name (small preset unless ``preset`` says otherwise);
* a run folder of ``mcdenoise train``: its ``config.json`` rebuilds the exact model configuration,
  then ``model.safetensors`` (final) or else the newest complete checkpoint is loaded; a checkpoint
  folder (``RUN/checkpoints/step_N``) loads that step with its run's configuration;
* a ``.safetensors`` file: its metadata (``model``, ``preset``, and ``model_config`` when present)
  names the model; otherwise ``model=`` must.

Shipped weights are ``shipped/<name>-<preset>.safetensors`` with a model card
``shipped/<name>-<preset>.json`` beside them (training and dataset commands, steps, wall time,
device, test metrics). Weights are read with safetensors only, never unpickled.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from mcdenoise.errors import McDenoiseError
from mcdenoise.io.run_folder import CONFIG_FILE, WEIGHTS_FILE, checkpoint_run, intact_checkpoint
from mcdenoise.models.base import MODELS, Denoiser, build_from_fields
from mcdenoise.models.builtin import load_builtin_models

__all__ = [
    "SHIPPED_DIR",
    "WeightsError",
    "ShippedWeights",
    "shipped",
    "shipped_weights",
    "load_weights",
    "load_denoiser",
    "model_from_config",
    "POST_TRAINING_FIELDS",
    "preset_differences",
]

SHIPPED_DIR = Path(__file__).resolve().parent / "shipped"


class WeightsError(McDenoiseError):
    """Weights are missing, unreadable, or do not fit the model they are loaded into."""


@dataclass(frozen=True)
class ShippedWeights:
    """One shipped model: ``weights`` (safetensors) and its parsed model ``card``."""

    name: str
    preset: str
    weights: Path
    card: dict[str, Any]


def _card_path(weights: Path) -> Path:
    return weights.with_suffix(".json")


def shipped() -> list[ShippedWeights]:
    """Every shipped model, sorted by name then preset (empty when none are shipped)."""
    out = []
    for w in sorted(SHIPPED_DIR.glob("*.safetensors")):
        name, _, preset = w.stem.rpartition("-")
        card: dict[str, Any] = {}
        if _card_path(w).is_file():
            try:
                card = json.loads(_card_path(w).read_text())
            except ValueError as e:
                raise WeightsError(f"{_card_path(w)}: model card is not valid JSON ({e})") from None
        out.append(ShippedWeights(name, preset, w, card))
    return out


def shipped_weights(name: str, preset: str = "small") -> ShippedWeights:
    """The shipped weights of ``name`` at ``preset``; one-line error listing what is shipped."""
    for s in shipped():
        if s.name == name and s.preset == preset:
            return s
    have = ", ".join(f"{s.name} ({s.preset})" for s in shipped()) or "none"
    raise WeightsError(f"no shipped weights for model {name!r} preset {preset!r}; shipped: {have}")


def model_from_config(name: str, preset: str, model_config: dict[str, Any] | None = None) -> Denoiser:
    """Build ``name`` from ``preset``, then apply the saved ``model_config`` fields (a run's or a card's)."""
    load_builtin_models()
    if name not in MODELS:
        raise WeightsError(f"unknown model {name!r}; registered: {', '.join(sorted(MODELS))}")
    entry = MODELS[name]
    if preset not in entry.presets:
        raise WeightsError(f"model {name!r} has no preset {preset!r}; presets: {', '.join(sorted(entry.presets))}")
    try:
        return build_from_fields(name, preset, model_config)
    except KeyError as e:
        raise WeightsError(e.args[0]) from None


def load_weights(model: torch.nn.Module, path: str | Path) -> None:
    """Load a safetensors state dict into ``model`` (strict); one-line error naming the file, also for
    non-finite (NaN/Inf) weights, which would denoise to an all-NaN image."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"{path}: weights file not found")
    try:
        state = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as e:
        raise WeightsError(f"{path}: not a readable safetensors file ({e})") from None
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise WeightsError(f"{path}: non-finite weights (NaN or Inf) in {len(bad)} tensor(s), first {bad[0]!r}; "
                           "the file is damaged or its training diverged")
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = str(e).strip().splitlines()
        detail = " ".join(s.strip() for s in first[1:3]) if len(first) > 1 else first[0]
        raise WeightsError(f"{path}: weights do not fit {type(model).__name__}: {detail[:300]}") from None


def _metadata(path: Path) -> dict[str, str]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as f:
            return dict(f.metadata() or {})
    except (SafetensorError, OSError, ValueError) as e:
        raise WeightsError(f"{path}: not a readable safetensors file ({e})") from None


def _model_config(meta: dict[str, str], path: Path) -> dict[str, Any] | None:
    """The ``model_config`` metadata of a weights file as a dict (None when absent); one line when malformed."""
    if "model_config" not in meta:
        return None
    try:
        cfg = json.loads(meta["model_config"])
    except ValueError as e:
        raise WeightsError(f"{path}: malformed model_config metadata ({e})") from None
    if not isinstance(cfg, dict):
        raise WeightsError(f"{path}: model_config metadata must be a JSON object, got {type(cfg).__name__}")
    return cfg


def _from_run(run: Path) -> tuple[Denoiser, dict[str, Any]]:
    checkpoint: Path | None = None
    owner = checkpoint_run(run)
    if owner is not None:
        checkpoint, run = run, owner  # runs/x/checkpoints/step_00001000: that step of run x
    try:
        doc = json.loads((run / CONFIG_FILE).read_text())
    except (OSError, ValueError) as e:
        raise WeightsError(f"{run / CONFIG_FILE}: cannot read the run's configuration ({e})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("train") or {}, dict):
        raise WeightsError(f"{run / CONFIG_FILE}: not a run configuration (expected a JSON object with a 'train' object)")
    if not isinstance(doc.get("model_config") or {}, dict):
        raise WeightsError(f"{run / CONFIG_FILE}: model_config must be a JSON object")
    train = doc.get("train") or {}
    name, preset = train.get("model"), train.get("preset", "small")
    if not isinstance(name, str):
        raise WeightsError(f"{run / CONFIG_FILE}: no model name in the run's configuration")
    model = model_from_config(name, preset, doc.get("model_config"))
    weights = run / WEIGHTS_FILE
    step: int | None = None
    if checkpoint is not None:
        weights = checkpoint / WEIGHTS_FILE
    elif not weights.is_file():
        ck = intact_checkpoint(run)
        if ck is None:
            raise WeightsError(f"{run}: run has neither {WEIGHTS_FILE} nor an intact checkpoint")
        weights, step = ck.path / WEIGHTS_FILE, ck.step
    load_weights(model, weights)
    if step is None:
        step = int(_metadata(weights).get("step", train.get("steps", 0)) or 0)
    label = run.name if checkpoint is None else f"{run.name}@{step}"
    return model, {"name": name, "preset": preset, "weights": str(weights), "source": "run", "step": step, "label": label}


#: Configuration fields set on weights after training (``scripts/reconfigure_weights.py``), which a
#: preset therefore does not fix.
POST_TRAINING_FIELDS = ("autoexposure", "consistency", "consistency_min_spp", "consistency_box")


def preset_differences(name: str, preset: str, config: dict[str, Any] | None) -> list[str]:
    """The fields (sorted) in which a saved model configuration differs from ``preset`` of
    ``name``, leaving out :data:`POST_TRAINING_FIELDS`: empty when the architecture is the preset's."""
    import dataclasses

    # Tuples become lists, as a run's config.json reads back.
    want = json.loads(json.dumps(dataclasses.asdict(model_from_config(name, preset).config), default=list))
    got = json.loads(json.dumps(dict(config or {}), default=list))
    return sorted(k for k in set(want) | set(got) if k not in POST_TRAINING_FIELDS and want.get(k) != got.get(k))


def shipped_name(spec: str, preset: str | None = None) -> tuple[str, str] | None:
    """``(model, preset)`` of shipped weights named by ``spec``: a registered name (``preset``, or
    ``small``) or ``NAME-PRESET`` as the shipped files are named (``kpcn-pixel``, ``combine-ens``);
    None when ``spec`` is neither. Whether such weights are shipped is :func:`shipped_weights`'s to say."""
    load_builtin_models()
    if spec in MODELS:
        return spec, preset or "small"
    name, _, pre = spec.rpartition("-")
    return (name, pre) if name in MODELS else None


def load_denoiser(spec: str | Path, *, preset: str | None = None, model: str | None = None,
                  device: torch.device | str = "cpu") -> tuple[Denoiser, dict[str, Any]]:
    """Resolve ``spec`` (registered name, shipped ``NAME-PRESET`` such as ``kpcn-pixel``, run folder or
    ``.safetensors`` file) to a model in eval mode.

    Returns ``(model, info)``; ``info`` has ``name``, ``preset``, ``weights`` (path), ``source``
    (``shipped``, ``run`` or ``file``), ``label`` (a short name for tables) and, for shipped
    weights, ``card``.
    """
    load_builtin_models()
    s = str(spec)
    p = Path(s)
    if p.is_dir():
        net, info = _from_run(p)
    elif p.is_file() or s.endswith(".safetensors"):
        if not p.is_file():
            raise WeightsError(f"{p}: no such weights file")
        meta = _metadata(p)
        name = model or meta.get("model")
        if not name:
            raise WeightsError(f"{p}: weights file does not name its model (no 'model' metadata); pass model=")
        pre = preset or meta.get("preset", "small")
        cfg = _model_config(meta, p)
        net = model_from_config(name, pre, cfg)
        load_weights(net, p)
        info = {"name": name, "preset": pre, "weights": str(p), "source": "file", "label": p.stem}
    elif (named := shipped_name(s, preset)) is not None:
        name, pre = named
        sw = shipped_weights(name, pre)
        net = model_from_config(name, sw.preset, sw.card.get("model_config"))
        load_weights(net, sw.weights)
        info = {"name": name, "preset": sw.preset, "weights": str(sw.weights), "source": "shipped", "label": s, "card": sw.card}
    else:
        raise WeightsError(f"{s}: neither a registered model ({', '.join(sorted(MODELS))}), a shipped NAME-PRESET, "
                           "a run folder, nor a weights file")
    return net.to(device).eval(), info
