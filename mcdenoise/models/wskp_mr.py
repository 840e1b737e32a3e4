"""``wskp_mr``: WSKP's multi-resolution variant for high-spp input (Sec. 5.2, Eq. 7).

A U-Net reads the same 10-channel LDR input as :mod:`mcdenoise.models.wskp`. At each of its
``levels`` resolutions a 1x1 head predicts ``N`` importance maps and ``N`` fusion logits (paper:
N = 2 kernels of sizes 3 and 5 per level) and, below the coarsest level, one blend-weight logit.
The demodulated irradiance (same effective albedo as ``wskp``, see
:func:`mcdenoise.models.wskp.effective_albedo`), box-downsampled to every level, is filtered there
with :func:`fused_importance_filter`; the levels are combined from the coarsest with Eq. 7
(``o = i_f - alpha U D i_f + alpha U i_c``, :func:`mcdenoise.ops.multiscale.multires_blend`, alpha a
sigmoid) and the effective albedo is multiplied back. Emitter pixels (albedo above 1) read albedo 1,
are filled from their neighbours and pass through unfiltered, as in ``wskp`` (:mod:`mcdenoise.models.emitters`). Inputs are edge-padded to a multiple of
``2**(levels-1)`` and the output cropped back, so any H, W works.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from mcdenoise.models.blocks import PointwiseConv
from mcdenoise.models.base import Denoiser, register_model
from mcdenoise.models.emitters import emitter_mask, fill_emitters, pass_through
from mcdenoise.models.wskp import _PAPER, INPUT_CHANNELS, wskp_input
from mcdenoise.ops.importance import fused_importance_filter
from mcdenoise.ops.multiscale import downsample2, multires_blend

__all__ = ["WSKPMRConfig", "WSKPMR"]


@dataclass
class WSKPMRConfig:
    """Configuration of the multi-resolution WSKP denoiser."""

    channels: tuple[int, ...] = (32, 48, 64)
    """U-Net width per level, finest first; its length is the number of levels (paper: 3 levels;
    the widths are in the paper's supplementary, which we do not have: our choice)."""
    kernel_sizes: tuple[int, ...] = (3, 5)
    """Fused kernel sizes at every level (paper: 3 and 5)."""
    demod_threshold: float = 0.05
    """Albedo below which demodulation is phased out (see :func:`mcdenoise.models.wskp.effective_albedo`)."""


def _double_conv(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1), nn.ReLU(inplace=True),
    )


class WSKPMR(Denoiser):
    """U-Net predicting importance maps, fusion and blend weights at 3 resolutions (Eq. 7)."""

    input_kind = "pixels"

    def __init__(self, config: WSKPMRConfig) -> None:
        super().__init__(config)
        ch = tuple(config.channels)
        if len(ch) < 1 or not config.kernel_sizes:
            raise ValueError(f"WSKPMR: need at least one level and one kernel size, got {config}")
        self.levels = len(ch)
        n = len(config.kernel_sizes)
        self.enc = nn.ModuleList(_double_conv(INPUT_CHANNELS if i == 0 else ch[i - 1], ch[i]) for i in range(self.levels))
        # Decoder level i reads the upsampled level i+1 decoder output and the level i encoder output.
        self.dec = nn.ModuleList(_double_conv(ch[i] + ch[i + 1], ch[i]) for i in range(self.levels - 1))
        # Every level: N importance + N fusion logits; all but the coarsest: + 1 blend logit.
        self.heads = nn.ModuleList(
            PointwiseConv(ch[i], 2 * n + (1 if i < self.levels - 1 else 0)) for i in range(self.levels)
        )

    def required_channels(self) -> list[str]:
        return ["radiance", "albedo", "normal", "depth"]

    def conv_trunks(self) -> list[str]:
        """Every double convolution of the U-Net (pooling, upsampling and heads stay float32)."""
        return [f"enc.{i}" for i in range(len(self.enc))] + [f"dec.{i}" for i in range(len(self.dec))]

    def features(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, 10, H, W) U-Net input: LDR colour, albedo, normal, depth."""
        return wskp_input(batch, self.config.demod_threshold)[0]

    def _pad(self, t: torch.Tensor) -> torch.Tensor:
        """Edge-pad (B, C, H, W) to a multiple of ``2**(levels-1)``: the kernels then see repeated
        border pixels rather than black."""
        m = 2 ** (self.levels - 1)
        ph, pw = (-t.shape[-2]) % m, (-t.shape[-1]) % m
        return F.pad(t, (0, pw, 0, ph), mode="replicate") if ph or pw else t

    def predict(
        self, batch: dict[str, torch.Tensor]
    ) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]]:
        """Per level, finest first: importance maps (B, N, H_l, W_l), fusion logits (B, N, H_l, W_l)
        and the Eq. 7 blend weight alpha (B, 1, H_l, W_l) in [0, 1] (None at the coarsest level).
        H_l, W_l: the padded size halved l times."""
        return self._levels(self.features(batch))

    def _levels(self, x: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]]:
        """:meth:`predict` from the (B, 10, H, W) U-Net input ``x`` (so forward builds it once)."""
        f = self._pad(x)
        skips = []
        for i, enc in enumerate(self.enc):
            if i > 0:
                f = F.avg_pool2d(f, 2)
            f = enc(f)
            skips.append(f)
        outs = [self.heads[-1](f)]
        for i in range(self.levels - 2, -1, -1):
            f = self.dec[i](torch.cat([F.interpolate(f, scale_factor=2.0, mode="nearest"), skips[i]], dim=1))
            outs.append(self.heads[i](f))
        outs.reverse()  # finest first
        n = len(self.config.kernel_sizes)
        # alpha is a sigmoid: Eq. 7 is an interpolation between the fine result and the fine result
        # with its low frequencies replaced by the coarse one; a raw logit would extrapolate.
        return [
            (z[:, :n], z[:, n : 2 * n], torch.sigmoid(z[:, 2 * n : 2 * n + 1]) if i < self.levels - 1 else None)
            for i, z in enumerate(outs)
        ]

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        emitters = emitter_mask(batch["albedo"])
        x, irr, albedo = wskp_input(fill_emitters(batch, emitters), self.config.demod_threshold)
        h, w = irr.shape[-2:]
        # bfloat16 under training autocast: the filters and blends run in the image's precision.
        levels = [tuple(t.to(irr.dtype) if t is not None else None for t in lv) for lv in self._levels(x)]
        sizes = tuple(self.config.kernel_sizes)
        irrs = [self._pad(irr)]
        for _ in range(self.levels - 1):
            irrs.append(downsample2(irrs[-1]))
        imp, fus, _ = levels[-1]
        result = fused_importance_filter(irrs[-1], imp, fus, sizes=sizes)
        for i in range(self.levels - 2, -1, -1):
            imp, fus, alpha = levels[i]
            fine = fused_importance_filter(irrs[i], imp, fus, sizes=sizes)
            result = multires_blend(fine, result, alpha)  # type: ignore[arg-type]
        return pass_through(result[..., :h, :w] * albedo, batch["radiance"], emitters)


@register_model(
    "wskp_mr",
    config_cls=WSKPMRConfig,
    presets={
        "paper": lambda: WSKPMRConfig(),
        "small": lambda: WSKPMRConfig(channels=(8, 12, 16)),
    },
    paper=_PAPER,
    description="multi-resolution WSKP: U-Net, 2 fused kernels (3, 5) at 3 levels, Eq. 7 blend",
)
class WSKPMRModel(WSKPMR):
    pass
