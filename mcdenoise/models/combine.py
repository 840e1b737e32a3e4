"""A learned combiner of candidate estimates (issue 20; design in docs/models/combine.md).

The candidates are images of the same pixels: OIDN 2.5.1's output (channel ``oidn``, computed by
the data side from the same input), with ``prefiltered`` also OIDN's output on guides it
prefiltered itself (``oidn_pf``), and the noisy mean (``radiance``). A small U-Net looks at
both, the guides and how far OIDN strays from the noisy mean relative to its variance, and
predicts per pixel one softmax over ``k x k`` taps of every candidate. The output is that weighted
sum:

    out(p) = sum_c sum_t w_{c,t}(p) * C_c(p + t),   w >= 0,  sum w = 1

so a constant image stays constant and no output exceeds the largest candidate value in its
``k x k`` neighbourhood: the combiner cannot invent radiance (Back et al. 2020 combine a noisy
and a denoised image with a kernel network; Firmino et al. 2022 blend noisy and OIDN per pixel;
Zheng et al. 2021 weight several denoisers per pixel). It starts as the identity on OIDN (centre
tap bias), so fine-tuning moves away from OIDN only where the data says so. With
``kernel_candidate`` a frozen pixel model of ours (kpcn-pixel) is one more candidate: its small
kernels do not spread an emitter into the halos OIDN makes (presets ``ens_kpcn`` and ``kpcn``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from mcdenoise.models.base import Denoiser, build_from_fields, register_model
from mcdenoise.models.blocks import UNet
from mcdenoise.models.combine_config import CombineConfig
from mcdenoise.models.emitters import as_reflectance, emitter_mask
from mcdenoise.models.kpcn import apply_kernels

__all__ = ["CombineConfig", "Combine", "combine_features"]

#: Floor of luminance denominators (radiance units; exposures vary, so small).
EPS = 1e-4
#: Logits are soft-clipped to (-LOGIT_BOUND, LOGIT_BOUND): weights can still differ by e^24, but
#: the softmax never rounds a tap to an exact 0 (which would also hide the receptive field from
#: the gradient probe of mcdenoise.infer.receptive) and never overflows.
LOGIT_BOUND = 12.0


#: Candidate channels, in the order of the predicted weights (``prefiltered``: PF_CANDIDATES).
CANDIDATES = ("oidn", "radiance")
PF_CANDIDATES = ("oidn", "oidn_pf", "radiance")
#: Feature channels: log OIDN, log noisy, albedo, normal, log relative deviation of the noisy
#: mean from OIDN; with the variance: log relative variance and the deviation in standard deviations;
#: with the prefiltered candidate: its log colour and its log relative deviation from OIDN.
N_FEATURES = 3 + 3 + 3 + 3 + 1
N_VARIANCE_FEATURES = 2
N_PF_FEATURES = 3 + 1
#: With ``own_kernel``: the log of the demodulated noisy mean (what the kernel filters).
N_OWN_FEATURES = 3
#: With ``emitter_feature``: the emitter mask, last.
N_EMITTER_FEATURES = 1
#: Added to the albedo before demodulating (KPCN's, Bako et al. 2017 Sec. 4.3).
ALBEDO_EPS = 0.00316


def _lum(x: torch.Tensor) -> torch.Tensor:
    # Rec. 709 weights; one expression keeps this op self-contained for the float64 tests.
    return 0.2126 * x[:, 0:1] + 0.7152 * x[:, 1:2] + 0.0722 * x[:, 2:3]


def demodulate(batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(noisy / (albedo + eps), albedo + eps)``, each (B, 3, H, W): the colour the own kernel
    filters and the factor that brings it back. Emitter pixels read albedo 1 (their albedo is
    their radiance in Cycles' passes)."""
    a = as_reflectance(batch["albedo"]).clamp_min(0) + ALBEDO_EPS
    return batch["radiance"].clamp_min(0) / a, a


def combine_features(batch: dict[str, torch.Tensor], use_variance: bool = False, prefiltered: bool = False,
                     kernel: torch.Tensor | None = None, own: bool = False, emitter: bool = False) -> torch.Tensor:
    """``(B, N_FEATURES [+ N_VARIANCE_FEATURES] [+ N_PF_FEATURES] [+ N_PF_FEATURES] [+ N_OWN_FEATURES]
    [+ N_EMITTER_FEATURES], H, W)`` inputs of the weight network, exposure-normalised where it
    matters (log colour; ratios, not differences). ``kernel``: the kernel-model candidate ``(B, 3,
    H, W)``, described like ``oidn_pf`` (its log colour and relative deviation from OIDN); ``own``:
    the log demodulated noisy mean the own kernel filters (:func:`demodulate`); ``emitter``: the
    emitter mask (``CombineConfig.emitter_feature``)."""
    oidn = batch["oidn"].clamp_min(0)
    noisy = batch["radiance"].clamp_min(0)
    lo, ln = _lum(oidn), _lum(noisy)
    # How far the noisy mean is from OIDN, relative to OIDN: the network judges from the neighbourhood
    # whether that is noise (OIDN right) or detail/highlight OIDN removed (noisy right).
    deviation = torch.log1p((ln - lo).abs() / (lo + EPS))
    feats = [torch.log1p(oidn), torch.log1p(noisy), batch["albedo"].clamp(0, 1), batch["normal"], deviation]
    if use_variance:
        var = _lum(batch["radiance_variance"].clamp_min(0))
        # Noise relative to the signal, and the deviation in standard deviations of the noisy mean.
        feats += [torch.log1p(var / (lo * lo + EPS)), torch.log1p((ln - lo) ** 2 / (var + EPS * EPS + 1e-3 * lo * lo))]
    if prefiltered:
        pf = batch["oidn_pf"].clamp_min(0)
        feats += [torch.log1p(pf), torch.log1p((_lum(pf) - lo).abs() / (lo + EPS))]
    if kernel is not None:
        kc = kernel.clamp_min(0)
        feats += [torch.log1p(kc), torch.log1p((_lum(kc) - lo).abs() / (lo + EPS))]
    if own:
        feats.append(torch.log1p(demodulate(batch)[0]))
    if emitter:
        feats.append(emitter_mask(batch["albedo"]).to(oidn.dtype))
    return torch.cat(feats, dim=1)


def max3x3(x: torch.Tensor) -> torch.Tensor:
    """(B, C, H, W) -> same: the maximum over each pixel's 3x3 neighbourhood, the edge repeated
    (= ``max_pool2d`` of the replicate-padded image). Separable, in shifted maxima: CPU
    ``max_pool2d`` also computes indices, 8x slower at 1080p (``benchmarks/bench_fast_paths.py
    --parts combine``)."""
    p = F.pad(x, (0, 0, 1, 1), mode="replicate")
    rows = torch.maximum(torch.maximum(p[..., :-2, :], p[..., 1:-1, :]), p[..., 2:, :])
    p = F.pad(rows, (1, 1, 0, 0), mode="replicate")
    out = torch.maximum(torch.maximum(p[..., :-2], p[..., 1:-1]), p[..., 2:])
    return out


def apply_weights(candidates: list[torch.Tensor], weights: torch.Tensor, k: int,
                  dilations: list[int] | None = None) -> torch.Tensor:
    """``sum_c sum_t weights[:, c*k*k + t] * candidates[c](p + d_c * t)`` -> (B, C, H, W).

    Reference implementation (unfold): ``weights`` (B, len(candidates)*k*k, H, W), normalised by the
    caller, taps in row-major order over ``t in [-k//2, k//2]^2``; ``dilations`` the ``d_c`` (None:
    all 1; refine's coarse candidates take their taps farther apart). Candidates are replicate-padded
    so border taps repeat the edge instead of adding zeros.
    """
    b, ch, h, w = candidates[0].shape
    r = k // 2
    if k == 1:  # one tap per candidate: a weighted sum, no unfold copies
        out = candidates[0] * weights[:, 0:1]
        for c in range(1, len(candidates)):
            out.addcmul_(candidates[c], weights[:, c : c + 1])
        return out
    out = torch.zeros_like(candidates[0])
    for c, img in enumerate(candidates):
        d = 1 if dilations is None else int(dilations[c])
        p = r * d
        padded = F.pad(img, (p, p, p, p), mode="replicate") if p else img
        taps = F.unfold(padded, k, dilation=d).view(b, ch, k * k, h, w)
        out = out + (taps * weights[:, c * k * k : (c + 1) * k * k].unsqueeze(1)).sum(dim=2)
    return out


class Combine(Denoiser):
    """Per-pixel softmax kernels over OIDN's output and the noisy mean (see the module docstring)."""

    input_kind = "pixels"
    #: The weight network's output may come back from a bfloat16 channels_last trunk as it is: the
    #: weights are a few channels (converted here), the own kernel's K*K logits are converted a row
    #: band at a time by :func:`~mcdenoise.models.kpcn.apply_kernels` (a whole-image conversion of
    #: 49 channels cost more than the network at 1080p).
    trunk_outputs_any_layout = True

    def __init__(self, config: CombineConfig) -> None:
        super().__init__(config)
        if config.kernel < 1 or config.kernel % 2 == 0:
            raise ValueError(f"kernel must be odd and >= 1, got {config.kernel}")
        k2 = config.kernel * config.kernel
        w = config.width
        n_in = N_FEATURES + (N_VARIANCE_FEATURES if config.use_variance else 0) + (N_PF_FEATURES if config.prefiltered else 0)
        self.names = PF_CANDIDATES if config.prefiltered else CANDIDATES
        self.kernel_model: Denoiser | None = None
        if config.kernel_candidate:
            name, _, preset = config.kernel_candidate.partition(":")
            sub = build_from_fields(name, preset or "small", config.kernel_candidate_config)
            if sub.input_kind != "pixels":
                raise ValueError(f"kernel_candidate {config.kernel_candidate!r} reads samples; the combiner takes pixel models only")
            self.kernel_model = sub.requires_grad_(False).eval()
            n_in += N_PF_FEATURES
        ko = config.own_kernel
        if ko < 0 or (ko and ko % 2 == 0) or config.own_kernel_loss < 0:
            raise ValueError(f"own_kernel must be 0 or odd and own_kernel_loss >= 0, got {ko}, {config.own_kernel_loss}")
        n_in += N_OWN_FEATURES if ko else 0
        n_in += N_EMITTER_FEATURES if config.emitter_feature else 0
        self.n_weights = (len(self.names) + (ko > 0) + (self.kernel_model is not None)) * k2
        self.net = UNet(n_in, self.n_weights + ko * ko, [(w, w)] * config.levels, (w, w), [(w, w)] * config.levels)
        if config.noisy_clamp_ref not in ("oidn", "min"):
            raise ValueError(f"noisy_clamp_ref must be 'oidn' or 'min', got {config.noisy_clamp_ref!r}")
        if not 0 < config.shrink <= 1:
            raise ValueError(f"shrink must be in (0, 1], got {config.shrink}")
        if not 0 <= config.start_logit < LOGIT_BOUND:
            raise ValueError(f"start_logit must be in [0, {LOGIT_BOUND}), got {config.start_logit}")
        with torch.no_grad():  # (nearly) the identity on OIDN at the start
            self.net.final.bias.zero_()
            self.net.final.weight.mul_(0.1)
            s = config.start_logit
            self.net.final.bias[k2 // 2] = s / (1 - s / LOGIT_BOUND)  # the raw value that soft-clips to s

    def required_channels(self) -> list[str]:
        own = list(self.names) + (["radiance_variance"] if self.config.use_variance else []) + ["albedo", "normal"]
        sub = self.kernel_model.required_channels() if self.kernel_model is not None else []
        return own + [c for c in sub if c not in own]

    def train(self, mode: bool = True) -> "Combine":
        super().train(mode)
        if self.kernel_model is not None:  # frozen: never in training mode
            self.kernel_model.eval()
        return self

    @property
    def autoexposure(self) -> float | None:
        """The kernel candidate's key: tiled inference then gives every tile the whole image's scale."""
        return self.kernel_model.autoexposure if self.kernel_model is not None else None

    def exposure_colour(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return self.kernel_model.exposure_colour(batch) if self.kernel_model is not None else batch["radiance"]

    def conv_trunks(self) -> list[str]:
        own = ["net"]
        sub = self.kernel_model.conv_trunks() if self.kernel_model is not None else []
        return own + [f"kernel_model.{n}" for n in sub]

    def kernel_output(self, batch: dict[str, torch.Tensor]) -> torch.Tensor | None:
        """``(B, 3, H, W)`` the kernel candidate's output (None without one). Its parameters are
        frozen, but gradients with respect to the inputs pass (the receptive-field probe of tiled
        inference follows them; a training batch needs none, so no graph is built)."""
        if self.kernel_model is None:
            return None
        return self.kernel_model(batch).to(batch["oidn"].dtype)

    def features(self, batch: dict[str, torch.Tensor], kernel: torch.Tensor | None = None) -> torch.Tensor:
        return combine_features(batch, self.config.use_variance, self.config.prefiltered, kernel, self.config.own_kernel > 0,
                                self.config.emitter_feature)

    def predict(self, batch: dict[str, torch.Tensor], kernel: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The weight network's two heads: (B, n_candidates * k * k, H, W) softmax weights
        (:meth:`weights`) and the own kernel's candidate (B, 3, H, W), None without ``own_kernel``."""
        raw = self.net(self.features(batch, kernel))
        own = None
        if self.config.own_kernel:
            colour, factor = demodulate(batch)
            logits = raw[:, self.n_weights :]
            # Training: the logits in the colour's dtype (the differentiable gather wants one dtype);
            # inference converts them a band at a time, whatever the trunk's layout.
            own = apply_kernels(colour, logits if not torch.is_grad_enabled() else logits.to(colour.dtype),
                                self.config.own_kernel) * factor
        return self._normalise(raw[:, : self.n_weights].to(batch["oidn"].dtype).contiguous()), own

    def weights(self, batch: dict[str, torch.Tensor], kernel: torch.Tensor | None = None) -> torch.Tensor:
        """(B, n_candidates * k * k, H, W) softmax weights (``kernel``: see :meth:`kernel_output`)."""
        return self.predict(batch, kernel)[0]

    def _normalise(self, raw: torch.Tensor) -> torch.Tensor:
        w = torch.softmax(raw / (1 + raw.abs() / LOGIT_BOUND), dim=1)
        a = self.config.shrink
        if a < 1:  # OIDN's centre tap is channel k*k // 2 (OIDN is the first candidate)
            centre = self.config.kernel * self.config.kernel // 2
            w = a * w + torch.nn.functional.one_hot(torch.tensor(centre), w.shape[1]).to(w).view(1, -1, 1, 1) * (1 - a)
        return w

    def candidates(self, batch: dict[str, torch.Tensor], kernel: torch.Tensor | None = None,
                   own: torch.Tensor | None = None) -> list[torch.Tensor]:
        """The candidate images, in ``self.names`` order (the noisy one clamped, see the config),
        then ``own`` (the own kernel's, :meth:`predict`) and ``kernel`` when given."""
        oidn, noisy = batch["oidn"], batch["radiance"]
        kc = self.config.kernel_clamp if kernel is not None or own is not None else 0.0
        if self.config.noisy_clamp > 0 or kc > 0:
            ref = oidn
            if self.config.noisy_clamp_ref == "min" and self.config.prefiltered:
                ref = torch.minimum(oidn, batch["oidn_pf"])
            if self.config.noisy_clamp > 0:
                bright = max3x3(ref.clamp_min(0))
                noisy = torch.minimum(noisy, self.config.noisy_clamp * bright + EPS)
            if kc > 0:  # per pixel, no neighbourhood: a kernel candidate may only be darker
                cap = kc * ref.clamp_min(0) + EPS
                kernel = torch.minimum(kernel, cap) if kernel is not None else None
                own = torch.minimum(own, cap) if own is not None else None
        out = [oidn, batch["oidn_pf"], noisy] if self.config.prefiltered else [oidn, noisy]
        return out + [c for c in (own, kernel) if c is not None]

    def forward_aux(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Training outputs: ``image`` (the forward pass) and, with ``own_kernel_loss``,
        ``own`` (the own kernel's unclamped candidate) for its own loss term."""
        out, own = self._forward(batch)
        return {"image": out, **({"own": own} if own is not None and self.config.own_kernel_loss > 0 else {})}

    def aux_loss_weights(self) -> dict[str, float]:
        """Weight of each :meth:`forward_aux` output's loss beside the image's."""
        return {"own": self.config.own_kernel_loss}

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return self._forward(batch)[0]

    def _forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor | None]:
        kernel = self.kernel_output(batch)
        weights, own = self.predict(batch, kernel)
        out = apply_weights(self.candidates(batch, kernel, own), weights, self.config.kernel)
        t = self.config.miss_halo
        if t > 0:
            noisy = batch["radiance"]
            miss = (batch["albedo"].abs().sum(1, keepdim=True) == 0) & (batch["normal"].abs().sum(1, keepdim=True) == 0)
            halo = miss & (_lum(out) > t * _lum(noisy.clamp_min(0)) + EPS)
            out = torch.where(halo, noisy, out)
        return out, own


_PAPER = ("Back et al. 2020 (deep combiner), Zheng et al. 2021 (ensemble denoising), Firmino et al. 2022 "
          "(progressive denoising): a per-pixel combination of OIDN and the noisy input")


@register_model(
    "combine",
    config_cls=CombineConfig,
    presets={
        "small": lambda: CombineConfig(),
        "small_var": lambda: CombineConfig(use_variance=True),
        "small_k3": lambda: CombineConfig(kernel=3),
        "paper": lambda: CombineConfig(width=32, levels=3, kernel=5, use_variance=True),
        "ens": lambda: CombineConfig(prefiltered=True),
        "ens_kpcn": lambda: CombineConfig(prefiltered=True, noisy_clamp=1.0, noisy_clamp_ref="min", kernel_candidate="kpcn:pixel"),
        "kpcn": lambda: CombineConfig(noisy_clamp=1.0, kernel_candidate="kpcn:pixel"),
        "own": lambda: CombineConfig(noisy_clamp=1.0, own_kernel=7, own_kernel_loss=0.5, kernel_clamp=1.0),
    },
    paper=_PAPER,
    description="U-Net -> per-pixel softmax kernels over OIDN 2.5.1's output and the noisy mean (ens_kpcn/kpcn: and a frozen kpcn-pixel)",
)
class CombineModel(Combine):
    pass
