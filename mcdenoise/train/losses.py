"""Training losses, registered by name, each marked as safe or not for noisy targets.

Every loss takes ``pred`` and ``target`` of the same shape (``(B, 3, H, W)`` linear HDR, or a
KPCN branch in its transformed domain) and returns a scalar: the mean over every element. Means
over equal-sized rows make a loss on ``B`` rows equal the average of its losses on two halves, which
is what lets ``world_size`` ranks with ``B / world_size`` rows each train the same model as one
process with ``B`` rows.

A loss is *unbiased for noisy targets* (Noise2Noise) when the expected gradient against a noisy
target ``t = y + n`` with ``E[n] = 0`` equals the gradient against the clean ``y``: true when the
loss is quadratic in ``t`` with a weight that does not depend on ``t``. L2 qualifies; relMSE
qualifies only with its denominator taken from the (detached) prediction instead of the target.
L1, SMAPE and the tonemapped/log losses are non-linear in ``t`` and converge to something else
(L1 to the median, for instance), so training with ``target="noisy"`` refuses them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

__all__ = ["Loss", "LOSSES", "get_loss", "register_loss", "RELMSE_EPS", "SMAPE_EPS"]

#: Denominator offset of relMSE (as in :func:`mcdenoise.eval.metrics.relmse`).
RELMSE_EPS = 1e-2
#: Denominator offset of SMAPE (Munkberg & Hasselgren 2020; Fan et al. 2021 Eq. 6).
SMAPE_EPS = 1e-2


@dataclass(frozen=True)
class Loss:
    """One registered loss.

    Attributes:
        name: registry key (CLI ``--loss``).
        fn: ``(pred, target) -> scalar`` mean over every element.
        unbiased_for_noisy_target: True when training against an independent noisy render gives,
            in expectation, the same gradient as the clean reference (see module docstring).
        description: one line for ``--help`` and docs.
    """

    name: str
    fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    unbiased_for_noisy_target: bool
    description: str

    def __call__(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        if pred.shape != target.shape:
            raise ValueError(f"loss {self.name}: prediction {tuple(pred.shape)} vs target {tuple(target.shape)}")
        return self.fn(pred, target)


LOSSES: dict[str, Loss] = {}


def register_loss(name: str, *, unbiased: bool, description: str) -> Callable[[Callable], Callable]:
    """Decorator adding ``fn(pred, target) -> scalar`` to :data:`LOSSES` under ``name``."""

    def deco(fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> Callable:
        if name in LOSSES:
            raise ValueError(f"loss {name!r} registered twice")
        LOSSES[name] = Loss(name, fn, unbiased, description)
        return fn

    return deco


def get_loss(name: str) -> Loss:
    """The registered loss ``name``, or a weighted sum of registered losses written
    ``"smape+0.1*relmse_ref"`` (terms ``NAME`` or ``WEIGHT*NAME``, weights > 0). A KeyError lists the
    known names. A sum is unbiased for noisy targets only when every term is."""
    if name in LOSSES:
        return LOSSES[name]
    terms = [_sum_term(part) for part in name.split("+")] if "+" in name else [None]
    if None in terms:
        raise KeyError(f"unknown loss {name!r}; known: {', '.join(sorted(LOSSES))}, or a sum such as "
                       "'smape+0.1*relmse_ref'")
    parts: list[tuple[float, Loss]] = terms  # type: ignore[assignment]

    def total(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        return sum(w * loss.fn(pred, target) for w, loss in parts)  # type: ignore[return-value]

    return Loss(name, total, all(loss.unbiased_for_noisy_target for _, loss in parts),
                " + ".join(f"{w:g} x {loss.name}" for w, loss in parts))


def _sum_term(part: str) -> tuple[float, Loss] | None:
    """``"0.1*relmse_ref"`` or ``"smape"`` as (weight, loss); None for an unknown loss or a weight
    that is not a finite number > 0."""
    w_text, _, term = part.strip().rpartition("*")
    try:
        weight = float(w_text) if w_text else 1.0
    except ValueError:
        return None
    return (weight, LOSSES[term]) if term in LOSSES and 0 < weight < math.inf else None


def _soft_tonemap(x: torch.Tensor) -> torch.Tensor:
    # x / (1 + |x|): SBMC's x / (1 + x) for x >= 0, odd-extended so that a negative prediction
    # (possible for direct-prediction models) cannot hit the pole at x = -1.
    return x / (1.0 + x.abs())


def _signed_log1p(x: torch.Tensor) -> torch.Tensor:
    # log(1 + x) for x >= 0, odd-extended for the same reason as _soft_tonemap.
    return torch.sign(x) * torch.log1p(x.abs())


@register_loss("l1", unbiased=False, description="mean |pred - target| (KPCN/DPCN, per branch then on the image)")
def l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (pred - target).abs().mean()


@register_loss("l2", unbiased=True, description="mean (pred - target)^2; unbiased for noisy targets")
def l2_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((pred - target) ** 2).mean()


@register_loss(
    "relmse",
    unbiased=True,
    description="mean (pred - target)^2 / (pred.detach()^2 + 0.01); the denominator never sees the target, "
    "so it stays unbiased for noisy targets (Noise2Noise)",
)
def relmse_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return _relative_l2(pred, target, pred.detach())


# Unlike `relmse`, the weight comes from the reference: a dim reference pixel filled with light (a
# highlight's halo) costs its full relative error, and a bright reference where the prediction is
# near zero costs at most 1 per unit of relative error, so there is no 1 / 0.01 pole on highlights.
# It rewards darkness, though (TRAINING.md, "Losses"): use it as a small term of a sum.
@register_loss("relmse_ref", unbiased=False, description="mean (pred - target)^2 / (target^2 + 0.01): the "
               "evaluation's relMSE itself, for clean references (biased for noisy targets)")
def relmse_ref_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return _relative_l2(pred, target, target.detach())


def _relative_l2(pred: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """mean (pred - target)^2 / (scale^2 + RELMSE_EPS); ``scale`` must carry no gradient."""
    return ((pred - target) ** 2 / (scale ** 2 + RELMSE_EPS)).mean()


@register_loss("smape", unbiased=False, description="mean |pred - target| / (|pred| + |target| + 0.01) (layer, WSKP)")
def smape_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((pred - target).abs() / (pred.abs() + target.abs() + SMAPE_EPS)).mean()


@register_loss("tonemapped_l2", unbiased=False, description="L2 between x / (1 + x) of both (SBMC and its ablations)")
def tonemapped_l2_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return ((_soft_tonemap(pred) - _soft_tonemap(target)) ** 2).mean()


@register_loss("log_l1", unbiased=False, description="L1 between log(1 + x) of both")
def log_l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (_signed_log1p(pred) - _signed_log1p(target)).abs().mean()
