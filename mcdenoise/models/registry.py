"""Model registry: every denoiser registers by name with a dataclass config and named presets
(:mod:`mcdenoise.models.base`, re-exported here); this module lists and builds them by name.

Batch convention shared by all models (channel names from :mod:`mcdenoise.data.channels`):

* pixel models (``input_kind == "pixels"``): ``batch[name]`` is ``(B, C, H, W)`` float32; per-pixel
  variances are under ``variance_name(name)``.
* sample models (``input_kind == "samples"``): ``batch[name]`` is ``(B, S, C, H, W)``;
  ``batch["scene_features"]`` is ``(B, len(SCENE_FEATURES))`` (zeros when absent).

Every model returns linear HDR radiance ``(B, 3, H, W)``.
"""

from __future__ import annotations

from typing import Any

import torch

from mcdenoise.data.channels import SCENE_FEATURES, base_name, is_variance_name, num_components
from mcdenoise.models.base import MODELS, Denoiser, ModelEntry, register_model
from mcdenoise.models.builtin import load_builtin_models

__all__ = [
    "Denoiser",
    "ModelEntry",
    "MODELS",
    "register_model",
    "build_model",
    "list_models",
    "synthetic_batch",
]


def _load_all() -> None:
    load_builtin_models()


def list_models() -> list[ModelEntry]:
    _load_all()
    return [MODELS[k] for k in sorted(MODELS)]


def build_model(name: str, preset: str = "small", *, weights: str | None = None, **overrides: Any) -> Denoiser:
    """Instantiate a registered model from one of its presets, with field overrides.

    ``weights="shipped"`` loads the weights shipped for ``(name, preset)`` (the shipped model
    card's configuration wins over the preset); a path loads that safetensors file (strict).
    See :mod:`mcdenoise.models.weights`.
    """
    _load_all()
    if name not in MODELS:
        raise KeyError(f"unknown model {name!r}; registered: {sorted(MODELS)}")
    entry = MODELS[name]
    if weights is None:
        return entry.cls(entry.config(preset, **overrides))
    from mcdenoise.models import weights as w

    if weights == "shipped":
        if overrides:
            raise ValueError("build_model: shipped weights fix the configuration; no field overrides")
        sw = w.shipped_weights(name, preset)
        model = w.model_from_config(name, preset, sw.card.get("model_config"))
        w.load_weights(model, sw.weights)
        return model
    model = entry.cls(entry.config(preset, **overrides))
    w.load_weights(model, weights)
    return model


def synthetic_batch(
    model: Denoiser,
    *,
    batch: int = 1,
    spp: int = 4,
    height: int = 16,
    width: int = 16,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float32,
) -> dict[str, torch.Tensor]:
    """Random but plausible inputs for ``model`` (positive radiance, unit normals, [0,1] albedo).

    Used by tests and FLOP counting; never by training on real data.
    """
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    out: dict[str, torch.Tensor] = {}
    sample = model.input_kind == "samples"
    for name in model.required_channels():
        if name == "scene_features":
            continue
        c = num_components(base_name(name))
        shape = (batch, spp, c, height, width) if sample else (batch, c, height, width)
        x = torch.rand(shape, generator=g, dtype=dtype)
        base = base_name(name)
        if is_variance_name(name):
            x = x * 0.1
        elif base in ("radiance", "diffuse", "specular"):
            # Heavy-tailed like MC noise: a few bright outliers.
            x = x * 2.0 / (1.0 - 0.9 * torch.rand(shape, generator=g, dtype=dtype))
        elif base.startswith("normal"):
            x = torch.nn.functional.normalize(x * 2 - 1, dim=-3)
        elif base.startswith("depth"):
            x = x * 10.0
        out[name] = x
    if sample and "diffuse" in out and "specular" in out and "radiance" in out:
        out["radiance"] = out["diffuse"] + out["specular"]
    if not sample and "diffuse" in out and "specular" in out and "radiance" in out:
        out["radiance"] = out["diffuse"] + out["specular"]
    if sample:
        out["scene_features"] = torch.rand((batch, len(SCENE_FEATURES)), generator=g, dtype=dtype)
    return out
