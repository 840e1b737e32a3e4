"""The denoisers that ship with mcdenoise: :func:`load_builtin_models` registers them all.

Each model module registers itself in :data:`mcdenoise.models.base.MODELS` when imported; code that
looks models up by name (:mod:`mcdenoise.models.registry`, :mod:`mcdenoise.models.weights`) calls
this first. Importing the package ``mcdenoise.models`` does the same.
"""

from __future__ import annotations

__all__ = ["load_builtin_models"]


def load_builtin_models() -> None:
    """Import (and so register) every built-in model; cheap after the first call."""
    from mcdenoise.models import combine, kpcn, layer, refine, sbmc, wskp, wskp_mr  # noqa: F401  (registration side effects)
