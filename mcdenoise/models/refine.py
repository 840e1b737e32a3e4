"""A learned second stage over a frozen model's output (campaign 29, issue 19).

A registered model (the ``base``, in practice the shipped per-sample ``layer-medium``) denoises
first and is frozen. A small U-Net then reads pixel features (the base output, the noisy mean,
albedo, normal, how far the noisy mean strays from the base relative to its noise) and predicts
per pixel one softmax over ``k x k`` taps of a few candidate images: the base output, the noisy
mean clamped to the base's 3x3 maximum, and the base output blurred at coarser scales with its
taps dilated by the same factor. The output is the weighted sum

    out(p) = sum_c sum_t w_{c,t}(p) * C_c(p + d_c * t),   w >= 0,  sum w = 1

so a constant image stays constant and no output exceeds the largest candidate value its taps
reach. It starts as (nearly) the identity on the base (centre-tap bias), so training moves away
from the base only where the data says so. It is the combiner's idea (:mod:`mcdenoise.models.combine`;
Back et al. 2020 combine a noisy and a denoised image with a kernel network) with our own model in
OIDN's place, and it adds the coarse candidates of a multi-scale kernel (Vogels et al. 2018 filter
at several scales and blend them per pixel): campaign 28 found layer-medium's 4-spp deficit against
OIDN at the pixel scale in some scenes and at 8-32-pixel blocks in others.

Emitter pixels (albedo above 1, Cycles' convention) pass through, and the candidates are filled
there from their neighbours first, as every kernel model here does, so a light never spreads
into the surfaces its taps reach.
"""

from __future__ import annotations

from contextlib import nullcontext

import torch
import torch.nn.functional as F

from mcdenoise.models.base import Denoiser, build_from_fields, register_model
from mcdenoise.models.blocks import UNet
from mcdenoise.models.combine import LOGIT_BOUND, _lum, apply_weights, max3x3
from mcdenoise.models.emitters import _tracing, as_reflectance, batch_emitter_mask, fill_from_neighbours, pass_through
from mcdenoise.models.exposure import EXPOSURE_SCALE, batch_exposure, check_key
from mcdenoise.models.refine_config import RefineConfig

__all__ = ["RefineConfig", "Refine", "blur", "context_features", "noisy_band", "power_mean", "refine_features",
           "N_CONTEXT", "N_FEATURES", "N_SPREAD", "spread_features", "sample_halves"]

#: Log colour of the base output and of the noisy mean, albedo, normal, the noisy mean's
#: relative deviation from the base and its relative variance.
N_FEATURES = 3 + 3 + 3 + 3 + 1 + 1
#: Context features (``RefineConfig.context``): emitter proximity at two radii, brightness context at two.
N_CONTEXT = 4
#: Spread features (``RefineConfig.spread``): the base's disagreement with itself over two halves of the samples,
#: per pixel and over 5x5.
N_SPREAD = 2
#: Radii of the emitter-proximity windows (5x5, 13x13) and of the brightness-context windows (9x9, 25x25).
NEAR_RADII = (2, 6)
GLOW_RADII = (4, 12)
#: Exponent of the power mean that stands in for a window's maximum (see :func:`power_mean`).
POWER = 4
#: Floor of luminance denominators at the autoexposure scale (key 0.18: a mid-grey image's
#: luminance is 0.18, so 1e-3 is about 7.5 stops below it).
EPS = 1e-3


def blur(x: torch.Tensor, f: int) -> torch.Tensor:
    """``(B, C, H, W)`` -> same: the mean over each pixel's ``(2f-1) x (2f-1)`` box, the edge
    repeated. Stride 1, so it commutes with shifts (tiles agree with the whole image); with taps
    ``f`` apart, neighbouring boxes overlap by a pixel, so no pixel is skipped."""
    if f <= 1:
        return x
    r = f - 1
    return F.avg_pool2d(F.pad(x, (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1)


def noisy_band(base: torch.Tensor, noisy: torch.Tensor, f: int, clamp: float,
               exclude: float | None = None) -> torch.Tensor:
    """``(B, C, H, W)`` -> same: ``base`` with its coarse band (:func:`blur` at ``f``) replaced by the
    noisy mean's, each noisy pixel first clamped to ``clamp`` times the base's 3x3 maximum:

        max(0, base + blur_f(m * (n - base)) / blur_f(m)),  n = min(noisy, clamp * max3x3(base))

    where ``m`` is 1 everywhere (``exclude`` None: ``base - blur_f(base) + blur_f(n)``), or 0 at the
    pixels whose base luminance exceeds ``exclude`` times its box mean (bright, sparse pixels: partly
    covered small emitters, whose coverage noise the box would spread into halos; campaign 32, step 3).

    Why: a blur of the base keeps the base's own low-frequency bias (campaign 29's coarse candidates
    did not lower it), while the noisy mean's block means are unbiased and their noise falls with the
    box's area; the clamp keeps a few fireflies from deciding the band (campaign 32, step 2).
    With ``noisy == base`` it returns ``base`` (for ``clamp >= 1``)."""
    n = torch.minimum(noisy, clamp * max3x3(base.clamp_min(0)))
    if exclude is None:
        return (base - blur(base, f) + blur(n, f)).clamp_min(0)
    lum = _lum(base.clamp_min(0))
    m = (lum <= exclude * blur(lum, f)).to(base.dtype)
    # Where a box keeps no pixel, blur(m) and the numerator are both 0: the band is the base there.
    return (base + blur(m * (n - base), f) / blur(m, f).clamp_min(1e-12)).clamp_min(0)


def power_mean(x: torch.Tensor, r: int, p: int = POWER) -> torch.Tensor:
    """``(B, C, H, W)`` >= 0 -> same: ``mean(x^p)^(1/p)`` over each pixel's ``(2r+1)^2`` window, the edge
    repeated. A soft maximum (one pixel of value v among n zeros gives ``v / n^(1/p)``), chosen over
    max pooling because its gradient reaches every pixel of the window: the receptive-field probe of
    tiled inference follows gradients, and a max pool's reach only its argmax, so tiles would be cut
    too tight. Homogeneous of degree 1, so ratios of it are exposure-invariant."""
    return F.avg_pool2d(F.pad(x.pow(p), (r, r, r, r), mode="replicate"), 2 * r + 1, stride=1).pow(1.0 / p)


def context_features(lum: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """``(B, N_CONTEXT, H, W)``: where bright things are around each pixel. ``lum`` (B, 1, H, W) the
    base output's luminance at the autoexposure scale, ``mask`` (B, 1, H, W) bool emitter pixels or None.

    Emitter proximity: the power mean of the mask over 5x5 and 13x13 (0 far from a light seen
    directly, 1 inside one). Brightness context: ``log`` of the power mean of the luminance over 9x9
    and 25x25 over the pixel's own, so a pixel near a light seen directly or in a reflection, whose
    neighbourhood falls off steeply, reads a large value and a flat dim wall reads about 0."""
    # The floor keeps the power mean's gradient finite on black windows, the cap its 4th power in float32.
    lum = lum.clamp(0, 1e6) + EPS
    near = torch.zeros_like(lum) if mask is None else mask.to(lum.dtype)
    feats = [power_mean(near, r) for r in NEAR_RADII] + [torch.log(power_mean(lum, r) / lum) for r in GLOW_RADII]
    return torch.cat(feats, dim=1)


def sample_halves(batch: dict[str, torch.Tensor]) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]] | None:
    """The batch's even- and odd-numbered samples as two batches (per-sample tensors are
    ``(B, S, C, H, W)``; the rest is shared), or None with fewer than two samples."""
    rad = batch["radiance"]
    if rad.dim() != 5 or rad.shape[1] < 2:
        return None
    return tuple({k: (v[:, i::2] if v.dim() == 5 else v) for k, v in batch.items()} for i in (0, 1))  # type: ignore[return-value]


def spread_features(lum: torch.Tensor, half_a: torch.Tensor, half_b: torch.Tensor) -> torch.Tensor:
    """``(B, N_SPREAD, H, W)``: how much the base's output changes with the samples it reads, an
    estimate of its own noise (the dual-buffer idea of Rousselle et al. 2012). ``lum`` (B, 1, H, W) the
    base output's luminance, ``half_a``/``half_b`` (B, 1, H, W) the luminance of the base run on each
    half of the samples, all at the autoexposure scale. ``log1p`` of the difference over the output,
    per pixel and as the root mean square over 5x5 (a smoother map of the same)."""
    d = (half_a - half_b).abs()
    # The floor keeps the root's gradient finite where the halves agree (one sample: everywhere).
    local = blur(d * d, 3).clamp_min(torch.finfo(d.dtype).tiny).sqrt()
    return torch.cat([torch.log1p(d / (lum + EPS)), torch.log1p(local / (blur(lum, 3) + EPS))], dim=1)


def refine_features(base: torch.Tensor, noisy: torch.Tensor, var_mean: torch.Tensor, albedo: torch.Tensor,
                    normal: torch.Tensor, scale: torch.Tensor | None, mask: torch.Tensor | None = None,
                    context: bool = False, halves: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """``(B, N_FEATURES [+ N_CONTEXT] [+ N_SPREAD], H, W)`` inputs of the head, exposure-normalised:
    ``base``, ``noisy`` (B, 3, H, W) radiance, ``var_mean`` (B, 3, H, W) the variance of the noisy mean,
    ``albedo`` and ``normal`` (B, 3, H, W) pixel means, ``scale`` (B,) the autoexposure scale (None:
    1); with ``context``, :func:`context_features` of the base and the emitter ``mask`` follow; with
    ``halves`` (the base's outputs (B, 3, H, W) on each half of the samples), :func:`spread_features`."""
    if scale is not None:
        s = scale.to(base.dtype).view(-1, 1, 1, 1)
        base, noisy, var_mean = base * s, noisy * s, var_mean * s * s
        if halves is not None:
            halves = (halves[0] * s, halves[1] * s)
    base, noisy = base.clamp_min(0), noisy.clamp_min(0)
    lb, ln = _lum(base), _lum(noisy)
    # Noise or detail? How far the noisy mean is from the base, relative to the base and to its noise.
    deviation = torch.log1p((ln - lb).abs() / (lb + EPS))
    rel_var = torch.log1p(_lum(var_mean.clamp_min(0)) / (lb * lb + EPS * EPS))
    feats = [torch.log1p(base), torch.log1p(noisy), albedo.clamp(0, 1), normal, deviation, rel_var]
    if context:
        feats.append(context_features(lb, mask))
    if halves is not None:
        feats.append(spread_features(lb, _lum(halves[0].clamp_min(0)), _lum(halves[1].clamp_min(0))))
    return torch.cat(feats, dim=1)


class Refine(Denoiser):
    """A frozen base model, then per-pixel softmax taps over its output (module docstring)."""

    def __init__(self, config: RefineConfig) -> None:
        super().__init__(config)
        k = config.kernel
        if k < 1 or k % 2 == 0:
            raise ValueError(f"refine: kernel must be odd and >= 1, got {k}")
        if any(int(f) < 2 for f in config.coarse):
            raise ValueError(f"refine: coarse factors must be >= 2, got {tuple(config.coarse)}")
        if not 0 <= config.start_logit < LOGIT_BOUND:
            raise ValueError(f"refine: start_logit must be in [0, {LOGIT_BOUND}), got {config.start_logit}")
        check_key("refine", config.autoexposure)
        name, _, preset = config.base.partition(":")
        if name == "refine":
            raise ValueError("refine: the base cannot be another refine stage")
        self.base = build_from_fields(name, preset or "small", config.base_config).requires_grad_(False).eval()
        self.input_kind = self.base.input_kind  # type: ignore[misc]  (per instance: the base's)
        self.dilations = [1] + ([1] if config.noisy else []) + [int(f) for f in config.coarse]
        k2 = k * k
        w = config.width
        n_in = N_FEATURES + (N_CONTEXT if config.context else 0) + (N_SPREAD if config.spread else 0)
        if config.spread and self.input_kind != "samples":
            raise ValueError(f"refine: spread needs a per-sample base, {config.base} reads pixels")
        if config.heads < 1:
            raise ValueError(f"refine: heads must be >= 1, got {config.heads}")

        def head() -> UNet:
            net = UNet(n_in, len(self.dilations) * k2, [(w, w)] * config.levels, (w, w), [(w, w)] * config.levels)
            with torch.no_grad():  # (nearly) the identity on the base output: its centre tap
                net.final.bias.zero_()
                net.final.weight.mul_(0.1)
                s = config.start_logit
                net.final.bias[k2 // 2] = s / (1 - s / LOGIT_BOUND)  # the raw value that soft-clips to s
            return net

        self.net = head()
        # Further heads of an ensemble (config.heads); the first keeps its name, so one-head files load as before.
        self.extra_heads = torch.nn.ModuleList([head() for _ in range(config.heads - 1)])

    def required_channels(self) -> list[str]:
        own = list(self.base.required_channels())
        extra = ["radiance", "albedo", "normal"] + (["radiance_variance"] if self.input_kind == "pixels" else [])
        return own + [c for c in extra if c not in own]

    def train(self, mode: bool = True) -> "Refine":
        super().train(mode)
        self.base.eval()  # frozen: never in training mode
        return self

    @property
    def autoexposure(self) -> float | None:
        """The base's key when it has one (tiled inference then gives both one scale), else ours."""
        key = self.base.autoexposure
        return key if key is not None else self.config.autoexposure

    def exposure_colour(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.base.exposure_colour(batch)

    def conv_trunks(self) -> list[str]:
        return ["net"] + [f"extra_heads.{i}" for i in range(len(self.extra_heads))] + [f"base.{n}" for n in self.base.conv_trunks()]

    def pixel_inputs(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """``(noisy, var_mean, albedo, normal)``, each (B, 3, H, W): the pixel means of the input and
        the variance of the radiance mean (0 with one sample)."""
        rad = batch["radiance"]
        if rad.dim() == 5:
            n = rad.shape[1]
            noisy = rad.mean(dim=1)
            var = rad.var(dim=1) / n if n > 1 else torch.zeros_like(noisy)
            albedo, normal = batch["albedo"].mean(dim=1), batch["normal"].mean(dim=1)
        else:
            noisy, var = rad, batch["radiance_variance"]
            albedo, normal = batch["albedo"], batch["normal"]
        return noisy, var, as_reflectance(albedo), normal

    def candidates(self, base: torch.Tensor, noisy: torch.Tensor) -> list[torch.Tensor]:
        """The candidate images, in the order of :attr:`dilations`: the base output, the clamped
        noisy mean (``noisy``), then the base blurred at each ``coarse`` factor."""
        out = [base]
        if self.config.noisy:
            out.append(torch.minimum(noisy, self.config.noisy_clamp * max3x3(base.clamp_min(0))))
        return out + [blur(base, int(f)) for f in self.config.coarse]

    def weights(self, feats: torch.Tensor) -> torch.Tensor:
        """(B, n_candidates * k * k, H, W) softmax weights from the head's features (the mean over
        the heads of an ensemble)."""
        ws = []
        for net in [self.net, *self.extra_heads]:
            raw = net(feats).to(feats.dtype)
            ws.append(torch.softmax(raw / (1 + raw.abs() / LOGIT_BOUND), dim=1))
        return ws[0] if len(ws) == 1 else sum(ws[1:], ws[0]) / len(ws)

    def _stage_inputs(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """``(features, base, noisy, emitter mask or None)``: the head's input (B, N_FEATURES, H, W)
        and the images its candidates are made of, lights filled from their neighbours."""
        # The base is frozen: training needs no graph through it. At inference gradients with
        # respect to the inputs pass (the receptive-field probe of tiled inference follows them).
        with torch.no_grad() if self.training else nullcontext():
            base = self.base(batch)
            halves = None
            if self.config.spread:
                split = sample_halves(batch)
                if split is not None and self.base.autoexposure and EXPOSURE_SCALE not in batch:
                    # The halves at the whole batch's exposure: tiles are given the whole image's scale
                    # (one for all three runs), so the whole image must use one too, or tiles would differ.
                    scale = batch_exposure(batch, self.base.exposure_colour(batch), self.base.autoexposure)
                    split = tuple({**h, EXPOSURE_SCALE: scale} for h in split)
                # One sample: no second opinion, the spread reads 0 (the two "halves" agree).
                halves = [base, base] if split is None else [self.base(h) for h in split]
        noisy, var, albedo, normal = self.pixel_inputs(batch)
        base = base.to(noisy.dtype)
        if halves is not None:
            halves = [h.to(noisy.dtype) for h in halves]
        mask = batch_emitter_mask(batch, self.required_channels())
        if mask is not None and not _tracing() and bool(mask.any()):
            # Lights out of every candidate the taps read; they come back by pass_through.
            base, noisy, var = (fill_from_neighbours(t, mask) for t in (base, noisy, var))
            if halves is not None:
                halves = [fill_from_neighbours(h, mask) for h in halves]
        s = batch_exposure(batch, self.exposure_colour(batch), self.autoexposure) if self.autoexposure else None
        feats = refine_features(base, noisy, var, albedo, normal, s, mask, self.config.context,
                                None if halves is None else (halves[0], halves[1]))
        return feats, base, noisy, mask

    def features(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, N_FEATURES [+ N_CONTEXT], H, W): what the head reads (:func:`refine_features`)."""
        return self._stage_inputs(batch)[0]

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        feats, base, noisy, mask = self._stage_inputs(batch)
        out = apply_weights(self.candidates(base, noisy), self.weights(feats), self.config.kernel, self.dilations)
        return pass_through(out, batch["radiance"], mask)


_PAPER = ("Back et al. 2020 (a kernel network combining a noisy and a denoised image), Vogels et al. 2018 "
          "(kernels at several scales blended per pixel): a second stage over our own per-sample model")


def _layer_medium() -> RefineConfig:
    return RefineConfig(base="layer:medium")


def _layer_medium_ctx() -> RefineConfig:
    return RefineConfig(base="layer:medium", context=True)


def _layer_medium_ctx_x2() -> RefineConfig:
    return RefineConfig(base="layer:medium", context=True, heads=2)


def _layer_medium_ctx_x3() -> RefineConfig:
    return RefineConfig(base="layer:medium", context=True, heads=3)


def _layer_medium_ctx_spread() -> RefineConfig:
    return RefineConfig(base="layer:medium", context=True, spread=True)


register_model(
    "refine",
    config_cls=RefineConfig,
    presets={"small": lambda: RefineConfig(), "paper": lambda: RefineConfig(width=32, levels=3),
             "layer_medium": _layer_medium, "layer_medium_ctx": _layer_medium_ctx,
             "layer_medium_ctx_x2": _layer_medium_ctx_x2, "layer_medium_ctx_x3": _layer_medium_ctx_x3,
             "layer_medium_ctx_spread": _layer_medium_ctx_spread},
    paper=_PAPER,
    description="a frozen base model (layer-medium), then per-pixel softmax 5x5 taps over its output, the clamped "
                "noisy mean and the output blurred at 2x and 4x",
)(Refine)
