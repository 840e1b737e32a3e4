"""Which model denoises an input: the user's (``--model NAME|WEIGHTS|oidn``) or the best one we have.

Without a model named (issue 20, "an automatic pick that is honest"): every shipped model
(:func:`mcdenoise.models.weights.shipped`) whose inputs the image has is a candidate, and so is
Open Image Denoise 2.5.1 ``high`` itself. They are ranked by the *third-party validation* results
in the model cards (``card["validation"]``: relMSE at :data:`RANK_SPP` spp on
``../shared/valscenes``, with OIDN's on the same images), never by the procedural test split. A
model is picked only when its card shows it better than OIDN there; otherwise OIDN is. A card's
``not_for`` (source -> why, e.g. ``{"blender": ...}``) keeps that model out of the pick for inputs
from that renderer (:attr:`Inputs.source`), where it was measured worse than OIDN. Only when
OIDN is not installed do the old rules apply: test relMSE, then :data:`FALLBACK_ORDER`.
"""

from __future__ import annotations

import functools
import json
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any

import torch

from mcdenoise.infer.sources import InputError, Inputs
from mcdenoise.models.registry import MODELS, Denoiser, _load_all

__all__ = ["FALLBACK_ORDER", "card_relmse", "card_validation", "missing_channels", "choose_model"]

#: Order among shipped models whose card gives no test relMSE (unknown names go last, by name).
FALLBACK_ORDER: tuple[str, ...] = (
    "sbmc", "layer_optimized", "layer", "layer_weighted", "pixel_splat", "sbmc_gather", "pixel_gather",
    "kpcn", "kpcn_single", "dpcn", "wskp_mr", "wskp",
)
#: spp whose relMSE ranks models when the card gives one per spp (the issue's 8 spp), else the lowest.
RANK_SPP = 8


def _as_float(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def card_relmse(card: dict[str, Any]) -> float | None:
    """The test relMSE of a model card, or None.

    Reads ``card["test"]``: the ``"model"`` row of its ``"all"`` subset (the card of
    :mod:`mcdenoise.models.ship`), else the first key containing ``relmse`` (any case), whose value is a number,
    or a mapping spp -> number (keys like ``8``, ``"8"`` or ``"8spp"``), of which the entry for
    :data:`RANK_SPP` spp is used, else the one with the fewest spp.
    """
    test = card.get("test") if isinstance(card, dict) else None
    if not isinstance(test, dict):
        return None
    # The form `mcdenoise.models.ship` writes: subsets -> subset -> spp -> method -> metrics, with
    # this model under "model" and the "all" subset covering every test image.
    subsets = test.get("subsets")
    if isinstance(subsets, dict) and subsets:
        per_spp = subsets.get("all") or next(iter(subsets.values()))
        if isinstance(per_spp, dict):
            test = {"relmse": {k: ((v or {}).get("model") or {}).get("relmse") for k, v in per_spp.items()
                               if isinstance(v, dict)}}
    for key, value in test.items():
        if "relmse" not in str(key).lower():
            continue
        if _as_float(value) is not None:
            return _as_float(value)
        if isinstance(value, dict):
            by_spp: dict[int, float] = {}
            for k, v in value.items():
                digits = "".join(ch for ch in str(k) if ch.isdigit())
                if digits and _as_float(v) is not None:
                    by_spp[int(digits)] = _as_float(v)  # type: ignore[assignment]
            if by_spp:
                return by_spp.get(RANK_SPP, by_spp[min(by_spp)])
    return None


def card_validation(card: dict[str, Any], spp: int = RANK_SPP) -> tuple[float, float] | None:
    """``(model relMSE, OIDN high relMSE)`` on the third-party validation scenes at ``spp``, from
    ``card["validation"]["spp"][str(spp)]`` (written by ``mcdenoise.models.ship --valscenes``), or None."""
    v = card.get("validation") if isinstance(card, dict) else None
    row = ((v or {}).get("spp") or {}).get(str(spp)) if isinstance(v, dict) else None
    if not isinstance(row, dict):
        return None
    mine = _as_float((row.get("model") or {}).get("relmse"))
    oidn = _as_float((row.get("oidn-high") or {}).get("relmse"))
    return (mine, oidn) if mine is not None and oidn is not None else None


def missing_channels(required: list[str], kind: str, inputs: Inputs) -> list[str]:
    """Channels of ``required`` (a model's ``required_channels()``) that ``inputs`` lacks.

    A sample model on an input without per-sample buffers lacks ``"per-sample buffers"`` first,
    then only the channels the input lacks even per pixel (a Blender file has radiance, albedo,
    normal and depth per pixel: naming them as missing sent users looking for passes they had).
    """
    need = [c for c in required if c != "scene_features"]
    if kind == "samples" and inputs.samples is None:
        have = inputs.channels("pixels")
        return (["per-sample buffers (an image folder of `mcdenoise render`)"]
                + [c for c in need if c not in have])
    have = inputs.channels(kind)
    return [c for c in need if c not in have]


def _refuse(label: str, name: str, missing: list[str]) -> InputError:
    """One line naming what is missing and, where a user can act on it, how to get it."""
    hints = []
    if any(c.endswith("_variance") for c in missing):
        hints.append("variances come from per-sample data (an image folder of `mcdenoise render`); "
                     "kpcn-pixel estimates them from the image instead")
    if {"diffuse", "specular"} & set(missing):
        hints.append("in Blender, turn on the Diffuse Direct, Indirect and Color passes for the diffuse/specular split")
    tail = f" ({'; '.join(hints)})" if hints else ""
    return InputError(f"model {name!r} needs channels that {label} lacks: {', '.join(missing)}{tail}")


def _oidn_info(why: str, inputs: Inputs) -> dict[str, Any]:
    """OIDN's info; ``channels`` are those it reads from ``inputs``: the colour, albedo when
    present and normal only beside it (``mcdenoise.data.oidn_input.oidn_guides``'s rule; it said
    albedo and normal also for a file that had neither)."""
    from mcdenoise.eval.oidn import version

    have = inputs.channels("pixels")
    guides = [c for c in ("albedo", "normal") if c in have] if "albedo" in have else []
    return {"name": "oidn", "preset": "high", "source": "library", "weights": f"Open Image Denoise {version()}",
            "label": "oidn", "why": why, "channels": ["radiance", *guides], "precision": "float32"}


#: Prepared models kept for repeated calls (``mcdenoise.denoise`` in a loop), newest last; loading,
#: folding and wrapping in bfloat16 cost ~15 ms a call, 10% of a fast model's time at 1080p.
_PREPARED: OrderedDict[tuple[Any, ...], tuple[Denoiser, dict[str, Any]]] = OrderedDict()
_PREPARED_MAX = 4
_PREPARED_LOCK = threading.Lock()


def _weights_identity(spec: str, preset: str | None) -> tuple[Any, ...] | None:
    """What names the weights ``spec`` loads (files' paths, inodes, sizes and change times), or None
    when it is not a single file (a run folder, whose checkpoint moves while it trains: never cached)."""
    from mcdenoise.models.weights import WeightsError, shipped_name, shipped_weights

    p = Path(spec)
    named = None if p.exists() else shipped_name(spec, preset)
    if p.is_file():
        files = [p]
    elif named is not None:
        try:
            w = shipped_weights(*named).weights
        except WeightsError:
            return None  # let load_denoiser say what is shipped
        files = [w, w.with_suffix(".json")]  # the card holds the model config
    else:
        return None
    ident: list[Any] = []
    for f in files:
        try:
            st = f.stat()
        except OSError:
            return None  # let load_denoiser say what is missing
        ident.append((str(f.resolve()), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    return tuple(ident)


def _load_prepared(spec: str, preset: str | None, device: torch.device | str,
                   precision: str) -> tuple[Denoiser, dict[str, Any]]:
    """``load_denoiser`` then ``prepare_inference``, reusing the result while the weights files are
    unchanged. The model is shared between calls: callers must not change it (inference does not)."""
    from mcdenoise.models.inference import prepare_inference
    from mcdenoise.models.weights import load_denoiser

    ident = _weights_identity(spec, preset)
    key = None if ident is None else (ident, spec, preset, str(torch.device(device)), precision)
    if key is not None:
        with _PREPARED_LOCK:
            hit = _PREPARED.get(key)
            if hit is not None:
                _PREPARED.move_to_end(key)
                return hit[0], dict(hit[1])
    model, info = load_denoiser(spec, preset=preset, device=device)
    model = prepare_inference(model, fast=True, precision=precision)
    if key is not None:
        with _PREPARED_LOCK:
            _PREPARED[key] = (model, info)
            while len(_PREPARED) > _PREPARED_MAX:
                _PREPARED.popitem(last=False)
    return model, dict(info)


@functools.lru_cache(maxsize=64)
def _arch_inputs(name: str, preset: str, config_json: str) -> tuple[tuple[str, ...], str]:
    """The channels and input kind of a shipped architecture (building one takes ~2 ms; the auto
    pick asks for each shipped model on every call)."""
    from mcdenoise.models.weights import model_from_config

    arch = model_from_config(name, preset, json.loads(config_json))
    return tuple(arch.required_channels()), arch.input_kind


def _fallback_rank(name: str) -> tuple[int, str]:
    return (FALLBACK_ORDER.index(name) if name in FALLBACK_ORDER else len(FALLBACK_ORDER), name)


def choose_model(inputs: Inputs, spec: str | None = None, *, device: torch.device | str = "cpu",
                 preset: str | None = None, precision: str = "float32") -> tuple[Denoiser, dict[str, Any]]:
    """Load the model for ``inputs``: ``spec`` (name, weights file or run folder) or the best shipped one.

    Returns ``(model in eval mode, info)``; ``info`` is :func:`mcdenoise.models.weights.load_denoiser`'s
    plus ``channels``, the input channels the model reads, and ``why``, one line on the choice.
    Raises :class:`InputError` (one line, naming the missing channels) when the model cannot run.
    ``precision``: of the convolution trunks (:func:`mcdenoise.models.inference.prepare_inference`);
    ``info["precision"]`` says which one was used.
    """
    from mcdenoise.models.weights import shipped

    from mcdenoise.eval.oidn import oidn_available
    from mcdenoise.infer.oidn_method import OIDN_NAME, OIDNMethod
    from mcdenoise.models.inference import resolve_precision

    _load_all()
    try:
        resolved = resolve_precision(precision, device)
    except ValueError as e:
        raise InputError(f"--precision: {e}") from None
    if spec == OIDN_NAME:
        if not oidn_available():
            raise InputError("--model oidn: Open Image Denoise is not installed (pip install 'pyoidn==2.5.1.0')")
        return OIDNMethod(), _oidn_info("as asked", inputs)
    if spec is not None:
        model, info = _load_prepared(spec, preset, device, resolved)
        missing = missing_channels(model.required_channels(), model.input_kind, inputs)
        if missing:
            raise _refuse(inputs.label, info["name"], missing)
        info["why"] = "as asked"
    else:
        candidates = []
        refused = []
        for sw in shipped():
            if sw.name not in MODELS or (preset is not None and sw.preset != preset):
                continue
            if inputs.source and inputs.source in (sw.card.get("not_for") or {}):
                continue  # measured worse than OIDN on that renderer's files (the card says why)
            needs, kind = _arch_inputs(sw.name, sw.preset, json.dumps(sw.card.get("model_config"), sort_keys=True))
            missing = missing_channels(list(needs), kind, inputs)
            if missing:
                refused.append((sw.name, missing))
                continue
            score = card_relmse(sw.card)
            rank = (0, score, "") if score is not None else (1, 0.0, "")
            candidates.append((rank, _fallback_rank(sw.name), sw, score))
        if not candidates and oidn_available() and "radiance" in inputs.channels("pixels"):
            return OIDNMethod(), _oidn_info("no shipped model has the inputs it needs here", inputs)
        if not candidates:
            if not refused:
                raise InputError("no shipped models are installed; pass --model NAME|WEIGHTS (a .safetensors file or a run folder)")
            # The model that misses the fewest channels says best what the input lacks.
            name, missing = min(refused, key=lambda r: (len(r[1]), _fallback_rank(r[0])))
            raise InputError(f"no shipped model can denoise {inputs.label}: the closest, {name!r}, needs "
                             f"{', '.join(missing)}")
        if oidn_available():
            beat = []
            for c in candidates:
                v = card_validation(c[2].card)
                if v is not None and v[0] < v[1]:
                    beat.append((v[0], c[1], c[2], v))
            if not beat:
                return OIDNMethod(), _oidn_info(
                    f"no shipped model for these inputs beats OIDN 2.5.1 high on the third-party validation scenes "
                    f"(relMSE at {RANK_SPP} spp in the model cards)", inputs)
            beat.sort(key=lambda b: (b[0], b[1]))
            _, _, best, (mine, oidn) = beat[0]
            model, info = _load_prepared(best.name, best.preset, device, resolved)
            info["why"] = (f"lowest third-party validation relMSE at {RANK_SPP} spp ({mine:.4g}, OIDN high {oidn:.4g}) "
                           "among the models whose inputs are present")
        else:
            candidates.sort(key=lambda c: (c[0][0], c[0][1], c[1]))
            _, _, best, score = candidates[0]
            model, info = _load_prepared(best.name, best.preset, device, resolved)
            info["why"] = (f"OIDN not installed; lowest test relMSE ({score:.4g}) among shipped models whose inputs are present"
                           if score is not None else
                           "OIDN not installed; first in the fixed order among shipped models whose inputs are present")
    info["channels"] = [c for c in model.required_channels() if c != "scene_features"]
    # Weights are loaded and WSKP's RepVGG branches folded (parity-tested in tests/test_fast_paths.py).
    info["precision"] = resolved
    return model, info
