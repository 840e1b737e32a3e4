"""What every denoiser is built on: the :class:`Denoiser` base class, the registration decorator
:func:`register_model` and the table :data:`MODELS` it fills.

The model modules (``kpcn``, ``sbmc``, ``layer``, ``wskp``, ``wskp_mr``) import this module only;
looking models up by name and building them is :mod:`mcdenoise.models.registry`, one layer up.
The batch convention the models share is described there too.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import torch
from torch import nn

from mcdenoise.models.exposure import batch_exposure

__all__ = ["Denoiser", "ModelEntry", "MODELS", "register_model", "coerce_field", "build_from_fields"]


class Denoiser(nn.Module):
    """Base class of all registered models.

    Subclasses set ``input_kind`` and implement :meth:`required_channels` and :meth:`forward`.
    """

    input_kind: ClassVar[str] = "pixels"  # "pixels" or "samples"

    def __init__(self, config: Any) -> None:
        super().__init__()
        self.config = config

    def required_channels(self) -> list[str]:
        """Names (vocabulary or ``*_variance``) that :meth:`forward` reads from the batch."""
        raise NotImplementedError

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:  # (B, 3, H, W)
        raise NotImplementedError

    @property
    def autoexposure(self) -> float | None:
        """The configuration's autoexposure key (:mod:`mcdenoise.models.exposure`); None without."""
        return getattr(self.config, "autoexposure", None)

    def exposure_of(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """``(B,)`` autoexposure scale the model applies to ``batch``, measured on
        :meth:`exposure_colour` or given as ``batch["exposure_scale"]``; None for a model without
        a key. Tiled inference measures it on the whole image and gives it to every tile."""
        if self.autoexposure is None:
            return None
        return batch_exposure(batch, self.exposure_colour(batch), self.autoexposure)

    def exposure_colour(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The radiance the autoexposure is measured on: ``(B, 3, H, W)`` or ``(B, S, 3, H, W)``."""
        return batch["radiance"]

    def pixel_consistency(self, out: Any, mean: Any, var_mean: Any, n: int) -> Any:
        """A pixel model's whole-image output ``(3, H, W)`` (numpy) clamped to its configuration's
        ``consistency`` around the input's per-pixel ``mean`` and variance of the mean over ``n``
        samples (:func:`mcdenoise.models.consistency.pixel_consistency_clamp`); ``out`` unchanged
        for a sample model (which clamps in its forward), without a ``consistency`` or a variance."""
        if self.input_kind != "pixels":
            return out
        from mcdenoise.models.consistency import pixel_consistency_clamp

        return pixel_consistency_clamp(out, mean, var_mean, n, getattr(self.config, "consistency", None),
                                       getattr(self.config, "consistency_min_spp", 2),
                                       getattr(self.config, "consistency_box", "mean"))

    def conv_trunks(self) -> list[str]:
        """Dotted names of the submodules that may run in bfloat16 and channels_last at inference
        (:func:`mcdenoise.models.inference.prepare_inference` with ``precision="bfloat16"``).

        A trunk maps feature maps to feature maps with convolutions, activations, pooling and
        resampling only: no exponentials, normalisations or kernel application, which stay in
        float32. Default: every :class:`~mcdenoise.models.blocks.UNet` of the model.
        """
        from mcdenoise.models.blocks import UNet

        return [n for n, m in self.named_modules() if isinstance(m, UNet)]


@dataclass
class ModelEntry:
    name: str
    cls: type[Denoiser]
    config_cls: type
    presets: dict[str, Callable[[], Any]]
    paper: str = ""
    description: str = ""

    def config(self, preset: str = "small", **overrides: Any) -> Any:
        if preset not in self.presets:
            raise KeyError(f"model {self.name!r} has no preset {preset!r}; presets: {sorted(self.presets)}")
        cfg = self.presets[preset]()
        return dataclasses.replace(cfg, **overrides) if overrides else cfg


MODELS: dict[str, ModelEntry] = {}


def coerce_field(default: Any, value: Any) -> Any:
    """JSON turned tuples into lists; give a field back the container type of the preset's value."""
    if isinstance(default, tuple) and isinstance(value, list):
        return tuple(coerce_field(d, v) for d, v in zip(default, value)) if len(default) == len(value) else tuple(value)
    return value


def build_from_fields(name: str, preset: str, fields: dict[str, Any] | None = None) -> "Denoiser":
    """Build registered model ``name`` from ``preset`` with saved configuration ``fields`` over it
    (a card's or a run's ``model_config``). The model's module must be registered already
    (:mod:`mcdenoise.models.registry` loads them all); KeyError names what is missing."""
    if name not in MODELS:
        raise KeyError(f"model {name!r} is not registered (registered: {', '.join(sorted(MODELS)) or 'none'})")
    entry = MODELS[name]
    cfg = entry.config(preset)
    if fields:
        names = {f.name for f in dataclasses.fields(cfg)}
        unknown = sorted(set(fields) - names)
        if unknown:
            raise KeyError(f"model {name!r}: saved configuration has fields this version lacks: {unknown}")
        cfg = dataclasses.replace(cfg, **{k: coerce_field(getattr(cfg, k), v) for k, v in fields.items()})
    return entry.cls(cfg)


def register_model(
    name: str,
    *,
    config_cls: type,
    presets: dict[str, Callable[[], Any]],
    paper: str = "",
    description: str = "",
) -> Callable[[type[Denoiser]], type[Denoiser]]:
    """Class decorator: ``@register_model("kpcn", config_cls=KPCNConfig, presets={...})``.

    ``presets`` must contain at least ``"paper"`` and ``"small"``.
    """

    def deco(cls: type[Denoiser]) -> type[Denoiser]:
        if name in MODELS:
            raise ValueError(f"model {name!r} registered twice")
        missing = {"paper", "small"} - set(presets)
        if missing:
            raise ValueError(f"model {name!r} lacks presets {sorted(missing)}")
        MODELS[name] = ModelEntry(name, cls, config_cls, dict(presets), paper, description)
        return cls

    return deco
