"""mcdenoise: neural denoising of Monte Carlo renderings.

Pipeline, one sub-package per stage: render -> data -> ops -> models -> train -> eval -> cli.

``mcdenoise.denoise(color, albedo, normal, depth, ...)`` denoises arrays (see docs/DENOISE.md); it
is imported on first use, so ``import mcdenoise`` stays light.
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"
__all__ = ["__version__", "denoise"]


def __getattr__(name: str) -> Any:
    # Lazy: the API pulls in torch and the models; the CLI's --version must not.
    if name == "denoise":
        from mcdenoise.infer.api import denoise

        return denoise
    raise AttributeError(f"module 'mcdenoise' has no attribute {name!r}")
