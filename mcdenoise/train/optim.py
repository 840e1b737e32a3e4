"""Optimizer, learning-rate schedule and the step that guards against non-finite values.

The schedule is a pure function of the step (:func:`lr_at`), so resuming needs only the step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mcdenoise.train.config import TrainConfig

__all__ = ["lr_at", "build_optimizer", "StepOutcome", "apply_gradients"]


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Learning rate of optimizer step ``step`` (0-based) out of ``cfg.steps``.

    Linear warm-up from ``lr / warmup_steps`` to ``lr`` over the first ``warmup * steps`` steps,
    then ``cosine`` decay to ``min_lr_fraction * lr`` at the last step, ``step`` decay (x0.1 at
    50 % and again at 75 % of the steps) or ``constant``.
    """
    assert cfg.lr is not None, "resolve the config first"
    n = cfg.steps
    warm = int(round(cfg.warmup * n))
    if step < warm:
        return cfg.lr * (step + 1) / warm
    if cfg.schedule == "constant":
        return cfg.lr
    if cfg.schedule == "step":
        return cfg.lr * (0.1 if step >= 0.5 * n else 1.0) * (0.1 if step >= 0.75 * n else 1.0)
    span = max(n - 1 - warm, 1)
    progress = min(max(step - warm, 0) / span, 1.0)
    floor = cfg.min_lr_fraction
    return cfg.lr * (floor + (1.0 - floor) * 0.5 * (1.0 + math.cos(math.pi * progress)))


def build_optimizer(model: torch.nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    """Adam with PyTorch's default betas/eps (as every paper here uses); lr is set per step."""
    return torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=lr_at(0, cfg))


@dataclass
class StepOutcome:
    """What one guarded optimizer step did.

    Attributes:
        loss: the loss value (may be non-finite when skipped).
        grad_norm: global gradient norm before clipping (non-finite when skipped for it).
        skipped: True when the update was dropped because the loss or a gradient was not finite.
    """

    loss: float
    grad_norm: float
    skipped: bool


def apply_gradients(
    params: list[torch.nn.Parameter], optimizer: torch.optim.Optimizer, loss_value: float, clip: float
) -> StepOutcome:
    """Clip and apply the gradients already in ``params`` unless anything is non-finite.

    A NaN/inf loss or gradient (a bad crop, an overflow under autocast) would poison Adam's moments
    for the rest of the run; dropping the update and counting it keeps the run usable. Every rank
    of a distributed run sees the same all-reduced gradients, so all ranks skip together.
    """
    max_norm = clip if clip > 0 else math.inf
    norm = torch.nn.utils.clip_grad_norm_(params, max_norm)
    norm_v = float(norm)
    if not (math.isfinite(loss_value) and math.isfinite(norm_v)):
        optimizer.zero_grad(set_to_none=True)
        return StepOutcome(loss_value, norm_v, True)
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    return StepOutcome(loss_value, norm_v, False)
