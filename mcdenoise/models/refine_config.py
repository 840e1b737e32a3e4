"""Configuration of the second stage over a frozen sample model (:mod:`mcdenoise.models.refine`),
each field with the measurement that motivated it."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["RefineConfig"]


@dataclass
class RefineConfig:
    """Sizes and candidates of the second stage.

    Attributes:
        base: ``"name:preset"`` of the registered model whose output the stage refines. It is part
            of the stage (its weights are saved in the stage's file) and frozen: training moves the
            head only.
        base_config: the base's configuration fields over its preset (a shipped card's
            ``model_config``), so the stage's file alone rebuilds it.
        width: channels of the head U-Net's levels.
        levels: head U-Net levels (pooling steps).
        kernel: taps per candidate per axis (odd).
        start_logit: initial logit of the base output's centre tap over every other tap; with
            ``kernel`` 5 and four candidates, 10 puts 99.5% of the weight there (the stage starts as
            the base).
    """

    base: str = "layer:small"
    base_config: dict | None = None
    width: int = 16
    levels: int = 2
    kernel: int = 5
    start_logit: float = 10.0
    coarse: tuple[int, ...] = (2, 4)
    """Scales of the coarse candidates: the base output box-blurred over (2f-1) x (2f-1) pixels
    (stride 1), its taps dilated by f (a 5x5 tap grid then spans 4f+1 pixels). Why: campaign 28's error bands put layer-medium's 4-spp deficit against OIDN high in the
    dark rooms lit by small sources at 8-32-pixel blocks (2.4-3.1x OIDN at 32), wider than its 17x17
    kernels, while running the same network on 2x2-merged samples (no learning) was worse at 2-8
    pixels: which scale to trust where must be learned per pixel."""
    noisy: bool = True
    """Add the noisy mean as a candidate, clamped to ``noisy_clamp`` times the base output's 3x3
    maximum. Why: in product shots layer-medium's deficit is fine-scale (the ratio to OIDN falls
    with the block size, campaign 28), detail the base smoothed away; the clamp keeps a firefly of
    the few samples out (the combiner's measurement, :class:`~mcdenoise.models.combine_config.CombineConfig`)."""
    noisy_clamp: float = 1.0
    context: bool = False
    """Four more head features that say where bright things are (:func:`~mcdenoise.models.refine.context_features`):
    the emitter mask max-pooled over 5x5 and 13x13, and how much brighter the base output gets within 9x9 and
    25x25. Why: campaign 29's head, reading per-pixel statistics only, smoothed the isolated outliers of dim
    rooms (third-party relMSE 0.62x layer-medium at the pixel scale) but lost 0.05-0.11 dB of held-out PSNR on
    the images with small bright emitters and nothing on the others: it could not tell the two apart."""
    spread: bool = False
    """Two more head features: how far the base's outputs on the even- and on the odd-numbered samples
    differ, per pixel and over 5x5 (:func:`~mcdenoise.models.refine.spread_features`); the base runs three
    times. Why: campaign 35 split the error over disjoint sample sets (``scripts/bias_variance_probe.py``).
    On the 54 third-party renderings at 4 spp refine-layer_medium_ctx_x2's bias part is below OIDN high's
    (0.066 against 0.078) and its variance part 1.7x (0.032 against 0.019), while on our own held-out
    images the base's variance is OIDN's: on unfamiliar content the base leaves noise, and nothing the
    head reads says where. The base's disagreement with itself does, whatever the content."""
    heads: int = 1
    """Heads over the one frozen base; their softmax weights are averaged, which is the average of
    their outputs (the taps are linear in the weights), so a convex kernel stays one. Why: two training
    seeds of one recipe (campaign 33) differed by 9.6% in third-party relMSE and 0.014 dB of held-out
    PSNR, as much as the effects being judged; a head is 30k parameters and the base runs once, so an
    ensemble of seeds costs little. Made from trained one-head files by ``scripts/refine_ensemble.py``:
    the first head keeps the name ``net``, the others are ``extra_heads.i``."""
    autoexposure: float | None = 0.18
    """Key of the features' exposure scale when the base has none (the base's key otherwise, so that
    tiled inference gives both one scale)."""
