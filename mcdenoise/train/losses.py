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

A *guided* loss also takes ``guide (B, 3, H, W)``, a brightness estimate made from the noisy input
alone (:func:`input_guide`). A weight that depends on the input but never on the target leaves the
loss's optimum at the conditional mean ``E[reference | input]``, so it can weight dim regions the way
the evaluation's relMSE does without rewarding a darker output (``relmse_ref``, whose weight comes from
the target, does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch
import torch.nn.functional as F

__all__ = ["Loss", "LOSSES", "get_loss", "guided_scale", "input_guide", "register_loss", "RELMSE_EPS", "SMAPE_EPS"]

#: Denominator offset of relMSE (as in :func:`mcdenoise.eval.metrics.relmse`).
RELMSE_EPS = 1e-2
#: Denominator offset of SMAPE (Munkberg & Hasselgren 2020; Fan et al. 2021 Eq. 6).
SMAPE_EPS = 1e-2


@dataclass(frozen=True)
class Loss:
    """One registered loss.

    Attributes:
        name: registry key (CLI ``--loss``).
        fn: ``(pred, target, guide) -> scalar`` mean over every element (``guide`` is None for an
            unguided loss).
        unbiased_for_noisy_target: True when training against an independent noisy render gives,
            in expectation, the same gradient as the clean reference (see module docstring).
        description: one line for ``--help`` and docs.
        guided: True when the loss needs ``guide``, the noisy input's :func:`input_guide`.
    """

    name: str
    fn: Callable[[torch.Tensor, torch.Tensor, torch.Tensor | None], torch.Tensor]
    unbiased_for_noisy_target: bool
    description: str
    guided: bool = False

    def __call__(self, pred: torch.Tensor, target: torch.Tensor, guide: torch.Tensor | None = None) -> torch.Tensor:
        if pred.shape != target.shape:
            raise ValueError(f"loss {self.name}: prediction {tuple(pred.shape)} vs target {tuple(target.shape)}")
        if self.guided and (guide is None or guide.shape != pred.shape):
            got = "none" if guide is None else str(tuple(guide.shape))
            raise ValueError(f"loss {self.name}: needs the input's guide of shape {tuple(pred.shape)}, got {got}")
        return self.fn(pred, target, guide if self.guided else None)


LOSSES: dict[str, Loss] = {}


def register_loss(name: str, *, unbiased: bool, description: str, guided: bool = False) -> Callable[[Callable], Callable]:
    """Decorator adding ``fn(pred, target) -> scalar`` (``fn(pred, target, guide)`` when ``guided``)
    to :data:`LOSSES` under ``name``."""

    def deco(fn: Callable[..., torch.Tensor]) -> Callable:
        if name in LOSSES:
            raise ValueError(f"loss {name!r} registered twice")
        call = fn if guided else (lambda pred, target, guide: fn(pred, target))
        LOSSES[name] = Loss(name, call, unbiased, description, guided)
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

    def total(pred: torch.Tensor, target: torch.Tensor, guide: torch.Tensor | None) -> torch.Tensor:
        return sum(w * loss.fn(pred, target, guide) for w, loss in parts)  # type: ignore[return-value]

    return Loss(name, total, all(loss.unbiased_for_noisy_target for _, loss in parts),
                " + ".join(f"{w:g} x {loss.name}" for w, loss in parts), any(loss.guided for _, loss in parts))


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


#: A guided loss's weight uses max(guide, target / GUIDE_RATIO) where the target is that much brighter.
GUIDE_RATIO = 10.0
#: `relmse_in_wide`'s ratio: the exception then changes the weight more than 2x on 0.5% of pixels at
#: 2-4 spp instead of 4.5% (campaign 19, our crops), at a cost of up to 100^2 per pixel.
WIDE_GUIDE_RATIO = 100.0


# The weight comes from the input, so a dim pixel the model fills with a highlight's light costs its
# full relative error (as in `relmse_ref`) while the optimum stays E[target | input], not below it.
# The one exception is a target over GUIDE_RATIO x the guide (a light's partial pixel that every
# sample missed at 2 spp, radiance up to 1e5): its weight comes from the target instead, so that it
# costs at most ~GUIDE_RATIO^2 rather than (1e3)^2 / 0.01 and drowning every other pixel
# (campaign 18's first tries); a perfect prediction still costs nothing. That weight depends on the
# target, so it is biased dark where it fires: a wider ratio fires less and matters only on targets
# above ~ratio / 10.
@register_loss("relmse_in", unbiased=False, guided=True, description=f"mean (pred - target)^2 / (max(guide, target / {GUIDE_RATIO:g})^2 "
               "+ 0.01), guide from the noisy input (max of its mean and 3x3 median): relMSE's weight without its "
               "reward for darkness")
def relmse_in_loss(pred: torch.Tensor, target: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
    return _relative_l2(pred, target, guided_scale(guide, target, GUIDE_RATIO))


@register_loss("relmse_in_wide", unbiased=False, guided=True, description=f"relmse_in with the exception at target > "
               f"{WIDE_GUIDE_RATIO:g} x guide: less dark bias, larger single-pixel costs")
def relmse_in_wide_loss(pred: torch.Tensor, target: torch.Tensor, guide: torch.Tensor) -> torch.Tensor:
    return _relative_l2(pred, target, guided_scale(guide, target, WIDE_GUIDE_RATIO))


def guided_scale(guide: torch.Tensor, target: torch.Tensor, ratio: float) -> torch.Tensor:
    """The guided losses' relMSE denominator scale, without gradient: the guide, or ``target / ratio``
    where the target is over ``ratio`` x the guide (the exception above). ``(B, 3, H, W)`` each."""
    return torch.maximum(guide, target / ratio).detach()


def input_guide(radiance: torch.Tensor) -> torch.Tensor:
    """The guided losses' brightness estimate, per channel and without gradient: the larger of each
    pixel's own sample mean and the 3x3 median (replicate border) of those means. ``radiance``:
    ``(B, S, 3, H, W)`` samples or ``(B, 3, H, W)``; returns ``(B, 3, H, W)`` float32.

    The median keeps a firefly or a highlight from spreading its brightness (a small weight) onto
    the dim pixels around it, which are where halos need charging; the pixel's own mean keeps a
    light one or two pixels wide, which the median alone would erase, from weighing 1 / 0.01."""
    x = radiance.detach().float()
    if x.dim() == 5:
        x = x.mean(dim=1)
    if x.dim() != 4:
        raise ValueError(f"input_guide: radiance must be (B, S, C, H, W) or (B, C, H, W), got {tuple(radiance.shape)}")
    b, c, h, w = x.shape
    patches = F.unfold(F.pad(x, (1, 1, 1, 1), mode="replicate"), kernel_size=3)  # (B, C*9, H*W)
    return torch.maximum(x, patches.view(b, c, 9, h * w).median(dim=2).values.view(b, c, h, w))


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


#: Side of the blocks whose means `lowpass_l1` compares: 8 px, so that a 96-px crop has 144 blocks
#: and a block at 4 spp averages 256 samples of the input, enough to tell darkening from noise.
LOWPASS_BLOCK = 8


# The pixel losses above leave each block's mean brightness free to drift: the relMSE-style terms
# reward a darker output where their weight comes from the target (and `relmse_in`'s exception
# does), and held-out and third-party images showed middle luminance quartiles darkened by 5-10%
# (TRAINING.md, campaigns 18-19). This term charges that drift directly and is blind to error that
# averages out within a block (residual noise, a shifted edge), which the pixel terms already cost.
# Its weight is the pooled target's, whose noise variance is 1/64 of a pixel's.
@register_loss("lowpass_l1", unbiased=False, description=f"mean |B(pred) - B(target)| / (B(target) + 0.01), B the "
               f"mean over {LOWPASS_BLOCK}x{LOWPASS_BLOCK} blocks (partial blocks at the border): local brightness "
               "drift, such as darkening, that pixel losses let through")
def lowpass_l1_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    p = F.avg_pool2d(pred, LOWPASS_BLOCK, LOWPASS_BLOCK, ceil_mode=True)
    t = F.avg_pool2d(target, LOWPASS_BLOCK, LOWPASS_BLOCK, ceil_mode=True)
    return ((p - t).abs() / (t.detach().abs() + RELMSE_EPS)).mean()
