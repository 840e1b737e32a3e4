"""Denoisers, registered by name. Importing this package registers all of them."""

from __future__ import annotations

from mcdenoise.models import kpcn, layer, sbmc, wskp, wskp_mr  # noqa: F401  (registration side effects)
from mcdenoise.models.registry import MODELS, Denoiser, build_model, list_models, register_model, synthetic_batch

__all__ = ["MODELS", "Denoiser", "build_model", "list_models", "register_model", "synthetic_batch"]
