"""Denoisers, registered by name. Importing this package registers all of them.

Each model module is imported below; add new ones to ``_MODULES``.
"""

from __future__ import annotations

import importlib

from mcdenoise.models.registry import MODELS, Denoiser, build_model, list_models, register_model, synthetic_batch

__all__ = ["MODELS", "Denoiser", "build_model", "list_models", "register_model", "synthetic_batch"]

_MODULES = ("kpcn", "sbmc", "layer", "wskp")

for _m in _MODULES:
    try:
        importlib.import_module(f"mcdenoise.models.{_m}")
    except ModuleNotFoundError as e:  # a model module not written yet
        if e.name != f"mcdenoise.models.{_m}":
            raise
