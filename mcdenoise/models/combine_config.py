"""Configuration of the combiner (:mod:`mcdenoise.models.combine`): sizes, candidates and rules,
each field with the measurement that motivated it."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["CombineConfig"]


@dataclass
class CombineConfig:
    """Sizes of the combiner.

    Attributes:
        width: channels of the weight U-Net's levels.
        levels: U-Net levels (pooling steps).
        kernel: taps per candidate per axis (odd).
        start_logit: initial logit of OIDN's centre tap over every other tap (identity start).
    """

    width: int = 16
    levels: int = 2
    kernel: int = 1
    start_logit: float = 7.0
    noisy_clamp: float = 8.0
    """The noisy candidate is clamped to this many times the brightest OIDN value in its 3x3
    neighbourhood (0 = off): a firefly of 1e5 in a dark region would otherwise reach the output
    through any weight the softmax leaves on it (measured: a fresh combiner with 1e-3 on the
    noisy tap had relMSE 1e5 on rich-world images, OIDN 0.24), while an emitter OIDN blurred
    keeps its peak (its OIDN neighbourhood is bright)."""
    noisy_clamp_ref: str = "oidn"
    """What ``noisy_clamp`` is relative to: ``"oidn"`` (plain OIDN's 3x3 maximum) or ``"min"`` (the
    3x3 maximum of the per-pixel minimum of the OIDN candidates; ``prefiltered`` only). Why
    ``"min"``: relMSE charges an overshoot at a dark pixel without bound but an undershoot of a
    bright one at most 1 per pixel, and the noisy candidate's overshoots are pixels that one sample
    of a few hit on a tiny, very bright thing (a sun in a chrome sphere: noisy 4056, reference
    0.46, plain OIDN 199, OIDN on prefiltered guides 5.4), where plain OIDN keeps much of the spike
    and so lets the clamp through."""
    use_variance: bool = False
    """Read the noisy pixel's variance (image folders with samples have it; Blender, pbrt and
    OIDN-style files do not). Off: the pixel-only combiner, usable on every input."""
    miss_halo: float = 10.0
    """Where every sample of a pixel missed the scene (albedo and normal exactly 0: this
    project's format for a miss) and the combination is brighter than this many times the noisy
    mean, the noisy mean is the output (0 = off). Such a pixel shows the background alone, which
    the samples see directly; a combination far above it is a halo that OIDN spread from an
    emitter beside it (measured on rich-world night skies: 0.007 in the reference, 2 from OIDN,
    50 from OIDN with prefiltered guides, 0.007 in the noisy mean). Measured with the shipped
    ``ens`` weights (``mcdenoise eval --data data/rich_val --split val``): 7.1x OIDN high's relMSE
    at 16 spp before the rule existed, 1.34x with it; the third-party figures did not move."""
    shrink: float = 1.0
    """Share of the learned weights in the output; the rest goes to OIDN's centre tap:
    ``w' = shrink * w + (1 - shrink) * onehot(OIDN)``, so the output is ``OIDN + shrink *
    (learned combination - OIDN)``, still a convex combination of the candidates. Below 1 it
    shrinks a combiner toward OIDN on scenes unlike its training data, where its choices are
    least reliable (``scripts/blend_probe.py``: on our own held-out images the mean relMSE ratio
    to OIDN high is lowest near 0.7, and the worst image moves toward OIDN as it falls)."""
    prefiltered: bool = False
    """Add a third candidate, ``oidn_pf``: OIDN with its guides prefiltered by OIDN first and
    passed as clean (OIDN's best mode for noisy guides). Measured before training (OIDN 2.5.1,
    ``scripts/oidn_variants_probe.py``): better than plain OIDN on most images, yet 13-30x worse in
    relMSE on one rich-world image of eight, where a bright bulb bleeds into a dark sky whose clean
    guides show no edge -- a per-pixel choice between the two is what the network learns."""
    kernel_candidate: str = ""
    """``"name:preset"`` of a registered pixel model (``"kpcn:pixel"``) whose output is one more
    candidate, the last; empty: none. The model is part of the combiner (its weights are saved in
    the combiner's file) and frozen: training moves only the weight network. Why: on our own
    held-out images (detail_ref 1-2 val, 8 spp) OIDN 2.5.1 spreads small bright emitters into
    halos over dark surroundings (relMSE 44, 377, 2.05 where the noisy input has 21.6, 9.1, 3.1),
    while kpcn-pixel's 9x9 kernels cannot carry an emitter further than 4 pixels (3.95, 0.64,
    0.079); the per-pixel oracle over OIDN and kpcn-pixel is 0.61-0.63x OIDN's relMSE on 45
    held-out images, and 0.48-0.50x with the noisy mean (docs/models/combine.md)."""
    kernel_clamp: float = 0.0
    """The kernel candidate is clamped to this factor times ``noisy_clamp``'s reference at the same
    pixel (no neighbourhood; 0 = off). Why: a kernel model's failure is the noisy input's, an
    overshoot, where one sample of a few hit a tiny bright thing and its kernel spreads that
    firefly (kpcn-pixel: relMSE 3339 and 1153 on two held-out images where OIDN has 0.095 and 9.9),
    while what it adds is darker than OIDN's halos, which no upper clamp touches. The 3x3
    neighbourhood the noisy clamp uses left relMSE 97 on the second image (9.8x OIDN's). The
    weight network still reads the unclamped output."""
    own_kernel: int = 0
    """Side K of a per-pixel kernel the weight network itself predicts (K*K more output
    channels) and applies to the noisy mean demodulated by the albedo, as KPCN filters diffuse
    irradiance; the result, remodulated, is one more candidate (after the noisy one; 0 = none).
    Why: a kernel model's candidate is what beats OIDN where it halos a small emitter
    (``kernel_candidate``), but kpcn-pixel costs 2x OIDN high at 1080p, and issue 20 leaves the
    combiner 0.5x; predicted by the same U-Net it costs one K*K softmax-gather. ``kernel_clamp``
    clamps it like the kernel model's candidate."""
    own_kernel_loss: float = 0.0
    """Weight of the own kernel candidate's loss against the target, added in training to the
    output's (the candidate then learns to denoise on its own, not only where the combination
    uses it; 0 = no such term)."""
    kernel_candidate_config: dict | None = None
    """The candidate model's configuration fields over its preset (a shipped card's
    ``model_config``), so the combiner's file alone rebuilds it."""
    emitter_feature: bool = False
    """Give the weight network one more input, the emitter mask (1 where an albedo value exceeds 1:
    :func:`~mcdenoise.models.emitters.emitter_mask`, Cycles' lights seen directly or in a mirror).
    Why: the albedo feature is clamped to [0, 1], so a light's pixel reads as a white wall, while
    at a light's edge every candidate can be far off (issue 21's room at 8 spp: reference 0.97,
    OIDN 7.0, the noisy mean and kpcn-pixel 11.9) and which one errs least there is a question of
    the pixel's kind the network could not see. Zero on data in our own convention (albedo <= 1),
    so it changes nothing there; ``scripts/reconfigure_weights.py --zero-new-inputs`` starts it
    from a combiner without it (zero weights on the new channel: the same outputs)."""
