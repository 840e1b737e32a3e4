"""Building blocks shared by the denoisers: per-sample fully connected stacks, a configurable U-Net,
padding helpers. (Kernel exponentiation lives in :mod:`mcdenoise.ops.kernels`.)

Conventions: per-pixel tensors are ``(B, C, H, W)``; per-sample tensors are ``(B, S, C, H, W)``.
All activations are leaky ReLU with slope 0.01 (SBMC Sec. 3.5, layer paper Appendix B).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "LEAK",
    "PointwiseConv",
    "FCStack",
    "UNet",
    "pad_to_multiple",
    "broadcast_samples",
    "signed_log1p",
]

#: Negative slope of every leaky ReLU in the SBMC and layer networks.
LEAK = 0.01


def signed_log1p(x: torch.Tensor) -> torch.Tensor:
    """``sign(x) * log(1 + |x|)``: compresses HDR values and unit-free scalars of any sign."""
    return torch.sign(x) * torch.log1p(torch.abs(x))


def _init_conv(m: nn.Conv2d) -> None:
    # He init for leaky-ReLU nets (SBMC Sec. 4.3), zero biases.
    nn.init.kaiming_normal_(m.weight, a=LEAK, nonlinearity="leaky_relu")
    if m.bias is not None:
        nn.init.zeros_(m.bias)


class PointwiseConv(nn.Conv2d):
    """A 1x1 convolution computed as one batched matrix product: (N, C_in, H, W) -> (N, C_out, H, W).

    Same parameters and state-dict keys as ``nn.Conv2d(C_in, C_out, 1)``, so weights saved by
    either load into the other. On the CPU oneDNN's 1x1 convolution on NCHW tensors of 8-42
    channels was most of SBMC's inference time; ``baddbmm`` over ``(C_out, C_in) @ (C_in, H*W)``
    is 1.3-4x faster for the widths our per-sample networks use (``benchmarks/bench_fast_paths.py
    --parts pointwise``) and computes the same sums (tested against ``F.conv2d`` in float64,
    gradchecked).
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = True) -> None:
        super().__init__(in_channels, out_channels, 1, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 4:
            return super().forward(x)
        n, c, h, w = x.shape
        if c > 1 and not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
            # NHWC (a bfloat16 trunk): oneDNN's 1x1 convolution takes it as it lies and returns
            # NHWC; reshaping to (N, C, H*W) for the matrix product would first copy it to NCHW
            # (the own combiner's 16 -> 52 head at 1080p: 14 ms against 69 ms,
            # benchmarks/bench_fast_paths.py --parts combine).
            return super().forward(x)
        wt = self.weight.view(self.out_channels, c).expand(n, -1, -1)
        x3 = x.reshape(n, c, h * w)
        y = torch.bmm(wt, x3) if self.bias is None else torch.baddbmm(self.bias.view(1, -1, 1), wt, x3)
        return y.view(n, self.out_channels, h, w)


class FCStack(nn.Module):
    """Fully connected layers applied independently at every sample/pixel (1x1 convolutions).

    ``forward(x, context)`` takes ``x`` of shape ``(..., C_in, H, W)`` (any number of leading dims,
    e.g. ``(B, S, C, H, W)``) and an optional per-pixel ``context`` ``(B, C_ctx, H, W)`` that is
    logically concatenated to every sample's features. The first layer is split into a per-sample
    and a per-pixel part, so the context is projected once per pixel instead of being copied S
    times: same function and parameter count as ``FC(cat(x, context))``, less memory.

    Args:
        in_channels: ``C_in``.
        widths: output width of each layer; the last one is the output width.
        context_channels: ``C_ctx`` (0 for none).
        last_activation: apply the leaky ReLU after the last layer too.
    """

    def __init__(
        self,
        in_channels: int,
        widths: Sequence[int],
        *,
        context_channels: int = 0,
        last_activation: bool = True,
    ) -> None:
        super().__init__()
        if not widths:
            raise ValueError("FCStack needs at least one layer")
        self.in_channels = in_channels
        self.context_channels = context_channels
        self.first = PointwiseConv(in_channels, widths[0])
        self.first_ctx = PointwiseConv(context_channels, widths[0], bias=False) if context_channels else None
        layers: list[nn.Conv2d] = []
        for a, b in zip(widths[:-1], widths[1:]):
            layers.append(PointwiseConv(a, b))
        self.rest = nn.ModuleList(layers)
        self.last_activation = last_activation
        self.out_channels = widths[-1]
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                _init_conv(m)

    def _act(self, x: torch.Tensor, is_last: bool) -> torch.Tensor:
        # In place: every activation follows a 1x1 convolution, whose output autograd does not
        # keep, and leaky ReLU's backward (slope > 0) needs only its result. Saves one
        # (N, width, H, W) tensor per layer, the largest tensors of the per-sample networks.
        return F.leaky_relu(x, LEAK, inplace=True) if (not is_last or self.last_activation) else x

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None) -> torch.Tensor:
        """``x`` (..., C_in, H, W), ``context`` (B, C_ctx, H, W) -> (..., widths[-1], H, W)."""
        lead = x.shape[:-3]
        c, h, w = x.shape[-3:]
        if c != self.in_channels:
            raise ValueError(f"FCStack expects {self.in_channels} input channels, got {c}")
        y = self.first(x.reshape(-1, c, h, w))
        if self.first_ctx is not None:
            if context is None:
                raise ValueError("FCStack was built with context channels but got no context")
            ctx = self.first_ctx(context)  # (B, W0, H, W)
            # Broadcast the per-pixel projection over all middle (sample) dims, in place (y is a
            # fresh convolution output) so no second (N, W0, H, W) tensor is made.
            b = ctx.shape[0]
            y.view(b, -1, *y.shape[-3:]).add_(ctx.unsqueeze(1))
        n = len(self.rest)
        y = self._act(y, n == 0)
        for i, layer in enumerate(self.rest):
            y = self._act(layer(y), i == n - 1)
        return y.reshape(*lead, y.shape[-3], h, w)


def pad_to_multiple(x: torch.Tensor, multiple: int, mode: str = "replicate") -> tuple[torch.Tensor, int, int]:
    """Pad ``(B, C, H, W)`` at the bottom/right so H and W are multiples of ``multiple``.

    Returns ``(padded, H, W)`` with the original size, to crop back with ``y[..., :H, :W]``.
    """
    h, w = x.shape[-2:]
    ph = (-h) % multiple
    pw = (-w) % multiple
    if ph == 0 and pw == 0:
        return x, h, w
    return F.pad(x, (0, pw, 0, ph), mode=mode), h, w


class _ConvBlock(nn.Sequential):
    """3x3 zero-padded convolutions, each followed by a leaky ReLU."""

    def __init__(self, in_channels: int, widths: Sequence[int]) -> None:
        layers: list[nn.Module] = []
        c = in_channels
        for w in widths:
            conv = nn.Conv2d(c, w, 3, padding=1)
            _init_conv(conv)
            # In place: the activation's input is a convolution output nobody else keeps.
            layers += [conv, nn.LeakyReLU(LEAK, inplace=True)]
            c = w
        super().__init__(*layers)
        self.out_channels = c


class UNet(nn.Module):
    """U-Net with 3x3 convs, 2x2 max-pooling, bilinear upsampling and concatenated skips.

    Level ``i`` of the encoder runs ``encoder[i]`` convolutions at resolution ``H / 2**i`` and its
    output is the skip of decoder level ``i``; the bottleneck runs at ``H / 2**len(encoder)``;
    ``decoder[0]`` is the coarsest decoder level. A final 1x1 convolution maps to ``out_channels``
    (no activation). Any H, W are accepted: the input is replicate-padded to a multiple of
    ``2**len(encoder)`` and every output is cropped back.

    Args:
        in_channels, out_channels: channel counts of input and output.
        encoder: widths of the convs of each encoder level, finest first.
        bottleneck: widths of the convs at the coarsest resolution.
        decoder: widths of the convs of each decoder level, coarsest first (same count as encoder).
        convs_per_level: if given, every level (encoder, bottleneck, decoder) runs exactly this
            many convolutions: a level's widths are padded with its last width, or cut. None (the
            default) runs as many as widths are given. SBMC's authors use 3 per level.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        encoder: Sequence[Sequence[int]],
        bottleneck: Sequence[int],
        decoder: Sequence[Sequence[int]],
        *,
        convs_per_level: int | None = None,
    ) -> None:
        super().__init__()
        if convs_per_level is not None:
            if convs_per_level < 1:
                raise ValueError(f"convs_per_level must be >= 1, got {convs_per_level}")
            n = convs_per_level

            def fit(ws: Sequence[int]) -> tuple[int, ...]:
                ws = tuple(ws)
                return (ws + (ws[-1],) * n)[:n] if ws else ws

            encoder = [fit(e) for e in encoder]
            decoder = [fit(d) for d in decoder]
            bottleneck = fit(bottleneck)
        if len(encoder) != len(decoder):
            raise ValueError("UNet needs as many decoder levels as encoder levels")
        if any(len(e) == 0 for e in encoder) or any(len(d) == 0 for d in decoder) or not bottleneck:
            raise ValueError("every UNet level needs at least one convolution")
        self.levels = len(encoder)
        self.enc = nn.ModuleList()
        c = in_channels
        skips = []
        for widths in encoder:
            blk = _ConvBlock(c, widths)
            self.enc.append(blk)
            c = blk.out_channels
            skips.append(c)
        self.bottleneck = _ConvBlock(c, bottleneck)
        c = self.bottleneck.out_channels
        self.dec = nn.ModuleList()
        self.decoder_channels: list[int] = []
        for i, widths in enumerate(decoder):
            blk = _ConvBlock(c + skips[self.levels - 1 - i], widths)
            self.dec.append(blk)
            c = blk.out_channels
            self.decoder_channels.append(c)
        self.final = PointwiseConv(c, out_channels)
        _init_conv(self.final)
        self.out_channels = out_channels

    @property
    def multiple(self) -> int:
        return 2**self.levels

    def forward(
        self, x: torch.Tensor, return_decoder: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, list[torch.Tensor]]:
        """``x`` (B, C_in, H, W) -> (B, C_out, H, W).

        With ``return_decoder``, also the decoder features of every level, coarsest first, level
        ``i`` cropped to ``ceil(H / 2**(levels-1-i)) x ceil(W / 2**(levels-1-i))``.
        """
        xp, h, w = pad_to_multiple(x, self.multiple)
        skips = []
        y = xp
        for blk in self.enc:
            y = blk(y)
            skips.append(y)
            y = F.max_pool2d(y, 2)
        y = self.bottleneck(y)
        decoded = []
        for blk in self.dec:
            # pop and inline: neither the skip nor the upsampled tensor outlives the concatenation
            # (at full resolution they are the U-Net's largest tensors after the concatenation).
            skip = skips.pop()
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = torch.cat([y, skip], dim=1)
            del skip
            y = blk(y)
            decoded.append(y)
        out = self.final(y)[..., :h, :w]
        if not return_decoder:
            return out
        crops = []
        for i, d in enumerate(decoded):
            s = 2 ** (self.levels - 1 - i)
            crops.append(d[..., : math.ceil(h / s), : math.ceil(w / s)])
        return out, crops


def broadcast_samples(x: torch.Tensor, spp: int) -> torch.Tensor:
    """``(B, C, H, W)`` -> ``(B, spp, C, H, W)`` view (no copy)."""
    return x.unsqueeze(1).expand(-1, spp, -1, -1, -1)
