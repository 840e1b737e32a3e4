"""WSKP (Fan, Wang, Huo, Bao 2021): weight-sharing kernel prediction for low-spp real-time denoising.

Per frame (Sec. 4, 5.1):

1. albedo demodulation: the filtered signal is the HDR irradiance ``radiance / a``, with ``a`` the
   effective albedo of :func:`effective_albedo` (the albedo itself on surfaces, 1 where the albedo
   is 0: sky, background, emitters);
2. the ImportanceNet (RepVGG blocks, 14 channels) reads a 10-channel LDR input: tonemapped colour
   (3), albedo (3), normal scaled to [0, 1] (3), depth as d / (1 + d) (1; crop-independent);
3. it predicts N importance maps and N fusion logits; map i becomes a softmax kernel of size
   ``k_i`` (Eq. 3), the irradiance is filtered with each (Eq. 4) and the results are averaged with
   the per-pixel softmax of the fusion logits (Eq. 5) -- all inside
   :func:`mcdenoise.ops.importance.fused_importance_filter`;
4. the same effective albedo is multiplied back (so the inverse is exact).

Emitter pixels (an albedo above 1: lights and sky as Cycles writes them) read albedo 1, their
colour is filled from their neighbours in what the network and the kernels see, and they pass
through unfiltered (:mod:`mcdenoise.models.emitters`); elsewhere that rule is the identity.

Temporal accumulation (Sec. 4.1) runs before the network on sequences and is kept apart from the
per-frame forward: :func:`temporal_accumulate` (re-exported from :mod:`mcdenoise.ops.temporal`).

``wskp_mr`` is the multi-resolution variant of Sec. 5.2 (model in :mod:`mcdenoise.models.wskp_mr`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from mcdenoise.models.base import Denoiser, register_model
from mcdenoise.models.emitters import as_reflectance, emitter_mask, fill_emitters, pass_through
from mcdenoise.models.consistency import ConsistencyOptions, check_consistency
from mcdenoise.models.exposure import check_key, scale_batch, unscale
from mcdenoise.ops.importance import fused_importance_filter
from mcdenoise.ops.temporal import temporal_accumulate

__all__ = [
    "WSKPConfig", "WSKP", "RepVGGBlock", "wskp_input", "effective_albedo", "tonemap_ldr", "temporal_accumulate",
]

_PAPER = "Fan, Wang, Huo, Bao, Real-time Monte Carlo Denoising with Weight Sharing Kernel Prediction Network, EGSR 2021"
#: Network input: LDR colour, albedo, normal, depth (Sec. 5.1).
INPUT_CHANNELS = 10


def tonemap_ldr(x: torch.Tensor) -> torch.Tensor:
    """HDR -> [0, 1): Reinhard ``x / (1 + x)`` then gamma 1/2.2 (any shape)."""
    x = x.clamp_min(0)
    # +1e-8 keeps the gamma's derivative finite at 0.
    return (x / (1 + x) + 1e-8) ** (1 / 2.2)


def effective_albedo(albedo: torch.Tensor, normal: torch.Tensor, threshold: float) -> torch.Tensor:
    """Albedo used for demodulation: (B, 3, H, W) albedo, (B, 3, H, W) normal -> (B, 3, H, W).

    Dividing by the raw albedo (+ a tiny eps) breaks where radiance is not albedo x irradiance: on
    sky, background and emitter pixels the albedo is 0 and the radiance is not, so the
    "irradiance" there is radiance / eps; the kernels spread it into neighbouring surfaces, whose
    albedo multiplies it back (issue 8, bug 4: outputs of 8.8 from inputs <= 0.67).  Two rules:

    1. The fraction of a pixel's samples that missed the scene counts as albedo 1 (its radiance is
       not modulated by any surface).  Pixel buffers are sample means and a miss has a zero normal,
       so that fraction is ``1 - |normal|`` (an upper bound where normals vary inside the pixel):
       ``a = albedo + (1 - |normal|)``.  An edge pixel mixing sky S and surface (albedo rho,
       irradiance E) then demodulates to a weighted mean of E and S, never to S / (coverage rho).
    2. Per channel, ``max(a, 1 - a / threshold)``: where a hit surface has (near) zero albedo --
       mirrors and glass in an albedo AOV, black emitters -- the albedo carries no texture, so the
       radiance is filtered as it is (effective albedo 1); the rule falls linearly to meet ``a``
       at ``threshold / (1 + threshold)`` and is ``a`` above.  It is continuous and never below
       that value, so demodulation amplifies a pixel's radiance at most ``1 + 1 / threshold``
       times; surfaces darker than the threshold are filtered partly as radiance (their texture
       is blurred a little, little in absolute terms).

    The same value multiplies the filtered irradiance back, so the inverse is exact.
    """
    # |normal| written out: torch.linalg.vector_norm over the 3 channels cost as much as the whole
    # importance filter on the CPU (79 ms at 960x540).  Clamping the squared norm to [tiny, 1]
    # before the root equals clamp(|n|, 0, 1) up to sqrt(tiny) ~ 1e-19 and keeps the gradient
    # finite (0) at zero normals, as norm's is.  (Both bounds floats: the ONNX exporter fails on
    # clamp(float, int).)
    n0, n1, n2 = normal[:, 0:1], normal[:, 1:2], normal[:, 2:3]
    squared = torch.addcmul(torch.addcmul(n0 * n0, n1, n1), n2, n2)
    coverage = squared.clamp(torch.finfo(squared.dtype).tiny, 1.0).sqrt()
    a = albedo + (1 - coverage)
    return torch.maximum(a, 1 - a / threshold)


def wskp_input(
    batch: dict[str, torch.Tensor], threshold: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """From the stored buffers: network input (B, 10, H, W), HDR irradiance (B, 3, H, W) and the
    effective albedo it was demodulated with (B, 3, H, W), see :func:`effective_albedo`. Emitter
    pixels (albedo above 1) read albedo 1 in both (:func:`mcdenoise.models.emitters.as_reflectance`)."""
    missing = [n for n in ("radiance", "albedo", "normal", "depth") if n not in batch]
    if missing:
        raise ValueError(f"WSKP: batch lacks channels {missing}")
    radiance = batch["radiance"]
    albedo = as_reflectance(batch["albedo"])
    # A fixed compressive map, not the paper's per-image [0, 1] scaling: a per-image maximum
    # depends on the crop or tile the network sees, so tiles of one image would disagree (seams).
    depth = batch["depth"].clamp_min(0)
    depth = depth / (1 + depth)  # in [0, 1) like the paper's range
    x = torch.cat([tonemap_ldr(radiance), albedo, (batch["normal"] + 1) * 0.5, depth], dim=1)
    a = effective_albedo(albedo, batch["normal"], threshold)
    return x, radiance / a, a


class RepVGGBlock(nn.Module):
    """Training-time block: 5x5, 3x3 and 1x1 conv+BN branches, plus BN identity when shapes allow,
    summed and (optionally) ReLU'd (WSKP Sec. 4.1, after Ding et al. 2021).

    :meth:`reparameterize` folds all branches into one 5x5 convolution with bias.
    ``forward``: (B, in_ch, H, W) -> (B, out_ch, H, W).
    """

    SIZES = (5, 3, 1)

    def __init__(self, in_ch: int, out_ch: int, activation: bool = True) -> None:
        super().__init__()
        self.in_ch, self.out_ch, self.activation = in_ch, out_ch, activation
        self.convs = nn.ModuleList(nn.Conv2d(in_ch, out_ch, k, padding=k // 2, bias=False) for k in self.SIZES)
        self.bns = nn.ModuleList(nn.BatchNorm2d(out_ch) for _ in self.SIZES)
        self.identity = nn.BatchNorm2d(out_ch) if in_ch == out_ch else None
        self.fused: nn.Conv2d | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.fused is not None:
            y = self.fused(x)
        else:
            y = sum(bn(conv(x)) for conv, bn in zip(self.convs, self.bns))
            if self.identity is not None:
                y = y + self.identity(x)
        # In place: y is a fresh sum or convolution output that no backward needs (ReLU's
        # backward uses its own result), so no second (B, out_ch, H, W) tensor is made.
        return F.relu(y, inplace=True) if self.activation else y

    @staticmethod
    def _fold(weight: torch.Tensor, bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
        """Conv weight (O, I, k, k) followed by eval-mode BN -> 5x5 weight and bias."""
        std = (bn.running_var + bn.eps).sqrt()
        scale = bn.weight / std
        pad = (5 - weight.shape[-1]) // 2
        w = F.pad(weight, (pad, pad, pad, pad)) * scale.view(-1, 1, 1, 1)
        return w, bn.bias - bn.running_mean * scale

    @torch.no_grad()
    def reparameterize(self) -> None:
        """Replace the branches by one equivalent 5x5 conv (uses BN running statistics)."""
        if self.fused is not None:
            return
        ref = self.convs[0].weight
        weight = torch.zeros((self.out_ch, self.in_ch, 5, 5), device=ref.device, dtype=ref.dtype)
        bias = torch.zeros(self.out_ch, device=ref.device, dtype=ref.dtype)
        for conv, bn in zip(self.convs, self.bns):
            w, b = self._fold(conv.weight, bn)
            weight += w
            bias += b
        if self.identity is not None:
            eye = torch.zeros((self.out_ch, self.in_ch, 1, 1), device=ref.device, dtype=ref.dtype)
            eye[torch.arange(self.out_ch), torch.arange(self.in_ch)] = 1
            w, b = self._fold(eye, self.identity)
            weight += w
            bias += b
        fused = nn.Conv2d(self.in_ch, self.out_ch, 5, padding=2).to(device=ref.device, dtype=ref.dtype)
        fused.weight.copy_(weight)
        fused.bias.copy_(bias)
        self.fused = fused
        del self.convs, self.bns, self.identity
        self.identity = None


@dataclass
class WSKPConfig(ConsistencyOptions):
    """Configuration of the single-resolution WSKP denoiser."""

    blocks: int = 6
    """Number of RepVGG blocks of the ImportanceNet (paper: 6, or 3 for the faster variant)."""
    channels: int = 14
    """Output channels of every block but the last (paper: 14)."""
    kernel_sizes: tuple[int, ...] = (3, 5, 7, 9, 11, 13)
    """Filter sizes of the fused kernels, one importance map and one fusion weight each (paper: 3..13)."""
    demod_threshold: float = 0.05
    """Albedo below which demodulation is phased out (see :func:`effective_albedo`; the paper gives
    no rule: it divides by the albedo)."""
    autoexposure: float | None = None
    """Key of the image-level autoexposure (:mod:`mcdenoise.models.exposure`; not in the paper):
    the radiance is scaled to it before the network and back after, so the output follows
    exposure exactly. None: the network sees the radiance as given."""
    consistency: float | None = None
    """Clamp each output pixel to this many (shrunk) standard errors around the input's pixel mean,
    where the input has per-pixel variances (:func:`mcdenoise.models.consistency.pixel_consistency_clamp`,
    applied by ``denoise`` and ``eval`` after the model; not in the paper). Set after training, on
    held-out images; None: no clamp."""


class WSKP(Denoiser):
    """ImportanceNet + importance-map kernels + kernel fusion, see the module docstring."""

    input_kind = "pixels"

    def __init__(self, config: WSKPConfig) -> None:
        super().__init__(config)
        if config.blocks < 1 or not config.kernel_sizes:
            raise ValueError(f"WSKP: need blocks >= 1 and at least one kernel size, got {config}")
        check_key("WSKP", config.autoexposure)
        check_consistency("WSKP", config.consistency, config.consistency_min_spp, config.consistency_box)
        n = len(config.kernel_sizes)
        chans = [INPUT_CHANNELS] + [config.channels] * (config.blocks - 1) + [2 * n]
        # The last block outputs logits (importance and fusion), so no ReLU there.
        self.net = nn.Sequential(
            *(RepVGGBlock(chans[i], chans[i + 1], activation=i < config.blocks - 1) for i in range(config.blocks))
        )

    def required_channels(self) -> list[str]:
        return ["radiance", "albedo", "normal", "depth"]

    def conv_trunks(self) -> list[str]:
        """The ImportanceNet (its logits enter the importance filter in float32)."""
        return ["net"]

    def features(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, 10, H, W) ImportanceNet input: LDR colour, albedo, normal, depth."""
        return wskp_input(batch, self.config.demod_threshold)[0]

    def predict(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Importance maps and fusion logits, each (B, N, H, W) with N = len(kernel_sizes)."""
        z = self.net(self.features(batch))
        n = len(self.config.kernel_sizes)
        return z[:, :n], z[:, n:]

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        emitters = emitter_mask(batch["albedo"])
        s = self.exposure_of(batch)  # of the image as given: a tile's scale is its whole image's
        inner = fill_emitters(batch, emitters)
        x, irradiance, albedo = wskp_input(inner if s is None else scale_batch(inner, s), self.config.demod_threshold)
        z = self.net(x)
        n = len(self.config.kernel_sizes)
        z = z.to(irradiance.dtype)  # bfloat16 under training autocast: the filter runs in the image's precision
        filtered = fused_importance_filter(irradiance, z[:, :n], z[:, n:], sizes=tuple(self.config.kernel_sizes))
        return pass_through(unscale(filtered * albedo, s), batch["radiance"], emitters)

    def reparameterize(self) -> "WSKP":
        """Fold every RepVGG block into one 5x5 conv for inference; puts the model in eval mode.

        The state dict changes keys (``net.i.fused.*``): to load a folded checkpoint, build the
        model, call this, then ``load_state_dict``.
        """
        self.eval()
        for block in self.net:
            block.reparameterize()
        return self

    temporal_accumulate = staticmethod(temporal_accumulate)


@register_model(
    "wskp",
    config_cls=WSKPConfig,
    presets={
        "paper": lambda: WSKPConfig(blocks=6),
        "paper3": lambda: WSKPConfig(blocks=3),
        "small": lambda: WSKPConfig(blocks=2, channels=8, kernel_sizes=(3, 5, 7)),
    },
    paper=_PAPER,
    description="RepVGG ImportanceNet -> 6 importance maps -> fused 3..13 softmax kernels on demodulated irradiance",
)
class WSKPModel(WSKP):
    pass
