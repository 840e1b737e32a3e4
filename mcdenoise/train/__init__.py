"""Training: one loop for every registered model (``mcdenoise train``, docs/TRAINING.md).

``from mcdenoise.train import train, TrainConfig`` works without importing torch until used.
"""

from __future__ import annotations

from typing import Any

__all__ = ["train", "TrainConfig", "TrainResult"]


def __getattr__(name: str) -> Any:
    # Lazy: `mcdenoise.train.data` and friends import torch; the package itself should not.
    if name in ("train", "TrainResult"):
        from mcdenoise.train import loop

        return getattr(loop, name)
    if name == "TrainConfig":
        from mcdenoise.train.config import TrainConfig

        return TrainConfig
    raise AttributeError(f"module 'mcdenoise.train' has no attribute {name!r}")
