"""SBMC: sample-based Monte Carlo denoising with a kernel-splatting network (Gharbi et al. 2019).

One network class, :class:`SBMC`, with two switches that give the paper's Table 2 ablations:

==============  ===========  ======  ==========================================================
name            per_sample   splat   what it is
==============  ===========  ======  ==========================================================
``sbmc``        True         True    the paper's model (Sec. 3, Algorithm 1)
``sbmc_gather`` True         False   "Gather": per-sample kernels applied as gathers, each sample
                                     index filtered as its own 1-spp image (Fig. 5a), then all
                                     normalised together; NOT permutation invariant, by design
``pixel_splat`` False        True    "PixelSplat": per-pixel mean and variance of the sample
                                     features as a 1-spp input, kernels splatted
``pixel_gather`` False       False   "PixelGather": the same pixel statistics, kernels gathered
==============  ===========  ======  ==========================================================

Pipeline (Algorithm 1): per-sample features -> ``E0 = FC(f)`` -> ``n`` times
``{C = mean_s(E); C' = UNet(C); E = FC(E, C')}`` -> ``K = FC(E, C')`` (21x21 logits per sample) ->
``I = sum K L / sum K`` (Eq. 1). Kernels act on linear radiance; the network sees log radiance.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from mcdenoise.data.channels import SCENE_FEATURES, num_components
from mcdenoise.models.blocks import FCStack, UNet, signed_log1p
from mcdenoise.models.base import Denoiser, register_model
from mcdenoise.models.emitters import ALBEDO_CHANNELS, as_reflectance, batch_emitter_mask, fill_emitters, pass_through
from mcdenoise.models.consistency import ConsistencyOptions, check_consistency, consistency_clamp
from mcdenoise.models.exposure import check_key, scale_batch, unscale
from mcdenoise.ops.gather import gather, gather_rows
from mcdenoise.ops.kernels import destination_max, per_destination_exp, per_pixel_exp
from mcdenoise.ops.splat import SplatAccumulator, normalize_splat, splat, splat_into_

__all__ = ["SBMCConfig", "SBMC", "SBMC_CHANNELS"]

#: Per-sample channels SBMC reads (Appendix A, restricted to what our renderer records). The
#: radiance split is log-transformed for the kernel predictor; ``radiance`` is also what is splatted.
SBMC_CHANNELS: tuple[str, ...] = (
    "radiance",
    "diffuse",
    "specular",
    "albedo_diffuse",
    "normal_diffuse",
    "depth_diffuse",
    "subpixel",
    "lens",
    "time",
    "lobes",
    "visibility",
)

#: Channels that are HDR or unbounded and are compressed with ``sign(x) log(1 + |x|)``.
_LOG_CHANNELS = frozenset({"radiance", "diffuse", "specular", "depth_diffuse", "depth"})


@dataclass
class SBMCConfig(ConsistencyOptions):
    """Configuration of :class:`SBMC` and its ablations."""

    per_sample: bool = True
    """True: one embedding and kernel per sample. False: reduce sample features to per-pixel mean and
    variance and treat them as a 1-spp input (PixelGather / PixelSplat)."""
    splat: bool = True
    """True: kernels are splatted (Eq. 1). False: kernels are gathered (Table 2 "Gather")."""
    channels: tuple[str, ...] = SBMC_CHANNELS
    """Per-sample vocabulary channels fed to the network; must include ``radiance``."""
    embed_width: int = 128
    """D_E, width of sample embeddings and context features (Sec. 3.2: 128)."""
    fc_width: int = 128
    """Width of the hidden layers of every per-sample fully connected stack (Sec. 3.5: 128)."""
    fc_layers: int = 3
    """Layers per fully connected stack (Sec. 3.5: 3)."""
    steps: int = 3
    """Alternating context/embedding updates, each with its own U-Net (Sec. 3.2: 3)."""
    unet_encoder: tuple[tuple[int, ...], ...] = ((128, 128), (256, 256))
    """Conv widths of each U-Net encoder level, finest first (Fig. 6)."""
    unet_bottleneck: tuple[int, ...] = (512, 512)
    """Conv widths at the U-Net's coarsest level (Fig. 6)."""
    unet_decoder: tuple[tuple[int, ...], ...] = ((256, 256), (128, 128))
    """Conv widths of each U-Net decoder level, coarsest first (Fig. 6)."""
    unet_convs_per_level: int | None = None
    """Convolutions per U-Net level (None: as many as the widths above list). The paper's text
    does not say (Fig. 6 is lost in our copy); the authors' code uses 3 (``num_convs=3``), so the
    ``paper`` preset sets 3."""
    kernel_size: int = 21
    """Side of the splat/gather kernel (Sec. 3.1: 21)."""
    eps: float = 1e-8
    """Added to the per-pixel weight sum before dividing (pixels no kernel reaches become 0)."""
    kernel_budget_mb: int = 1024
    """Bound on the memory of the per-sample kernels (and of the per-sample FC temporaries) that
    exist at once. Without gradients (inference) the per-sample networks and the kernels run one
    band of rows at a time, sized to this budget (splat: two passes, per-destination max then
    splat). With gradients (training) the splat variants generate kernels a chunk of samples at a
    time once all samples' kernels would exceed it. Same result either way."""
    autoexposure: float | None = None
    """Key of the image-level autoexposure (:mod:`mcdenoise.models.exposure`; not in the paper):
    the radiance is scaled to it before the network and back after, so the output follows
    exposure exactly. None: the network sees the radiance as given."""
    consistency: float | None = None
    """Clamp each output pixel to this many (shrunk) standard errors around the mean of its own
    samples (:mod:`mcdenoise.models.consistency`; not in the paper). Set after training, on held-out
    images; None: no clamp."""


def _paper(**kw: object) -> SBMCConfig:
    return SBMCConfig(unet_convs_per_level=3, **kw)  # type: ignore[arg-type]


def _small(**kw: object) -> SBMCConfig:
    return SBMCConfig(
        embed_width=16,
        fc_width=16,
        fc_layers=2,
        steps=2,
        unet_encoder=((16,), (32,)),
        unet_bottleneck=(32,),
        unet_decoder=((32,), (16,)),
        kernel_size=11,
        **kw,  # type: ignore[arg-type]
    )


class SBMC(Denoiser):
    """Sample-based kernel-splatting denoiser and its Table 2 ablations (see module docstring).

    Input: per-sample channels ``(B, S, C, H, W)`` for each name in ``config.channels`` and
    ``scene_features`` ``(B, 5)``. Output: linear HDR radiance ``(B, 3, H, W)``. Any S >= 1, H, W.
    """

    input_kind = "samples"

    def __init__(self, config: SBMCConfig) -> None:
        super().__init__(config)
        cfg = config
        if "radiance" not in cfg.channels:
            raise ValueError("SBMC needs the 'radiance' channel: it is what the kernels filter")
        if cfg.kernel_size % 2 != 1 or cfg.kernel_size < 1:
            raise ValueError(f"kernel_size must be odd, got {cfg.kernel_size}")
        if cfg.steps < 1 or cfg.fc_layers < 1:
            raise ValueError("steps and fc_layers must be >= 1")
        check_key("SBMC", cfg.autoexposure)
        check_consistency("SBMC", cfg.consistency, cfg.consistency_min_spp, cfg.consistency_box)
        self.sample_features = sum(num_components(c) for c in cfg.channels)
        n_in = (2 * self.sample_features if not cfg.per_sample else self.sample_features) + len(SCENE_FEATURES)
        d = cfg.embed_width
        hidden = [cfg.fc_width] * (cfg.fc_layers - 1)
        self.embed0 = FCStack(n_in, hidden + [d])
        self.unets = nn.ModuleList(
            UNet(d, d, cfg.unet_encoder, cfg.unet_bottleneck, cfg.unet_decoder,
                 convs_per_level=cfg.unet_convs_per_level)
            for _ in range(cfg.steps)
        )
        self.embeds = nn.ModuleList(FCStack(d, hidden + [d], context_channels=d) for _ in range(cfg.steps))
        k2 = cfg.kernel_size**2
        self.kernel = FCStack(d, hidden + [k2], context_channels=d, last_activation=False)

    def required_channels(self) -> list[str]:
        return list(self.config.channels)

    def features(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Network input and the radiance to filter.

        Returns ``(f, L)``: ``f`` is ``(B, S', F, H, W)`` and ``L`` is ``(B, S', 3, H, W)`` linear
        radiance, with ``S' = S`` per sample or ``S' = 1`` (pixel mean) for the pixel ablations.
        HDR channels and depth are ``sign(x) log(1 + |x|)`` compressed; scene features likewise
        (their units vary by scene: degrees, world units) and are broadcast to every sample.
        """
        cfg = self.config
        xs = [batch[name] for name in cfg.channels]
        for name, x in zip(cfg.channels, xs):
            if x.dim() != 5:
                raise ValueError(f"SBMC expects per-sample '{name}' of shape (B, S, C, H, W), got {tuple(x.shape)}")
        # Emitter pixels read albedo 1 (mcdenoise.models.emitters).
        xs = [as_reflectance(x) if name in ALBEDO_CHANNELS else x for name, x in zip(cfg.channels, xs)]
        dtype = xs[0].dtype
        for x in xs[1:]:
            dtype = torch.promote_types(dtype, x.dtype)
        radiance = batch["radiance"]
        b, s, _, h, w = radiance.shape
        n_f = self.sample_features
        n_g = len(SCENE_FEATURES)
        s_out = s if cfg.per_sample else 1
        n_out = n_f if cfg.per_sample else 2 * n_f
        # Written into one preallocated tensor group by group (no list of parts plus their
        # concatenation: at 1080p and 8 spp that is 2.8 GB saved).
        f = radiance.new_empty((b, s_out, n_out + n_g, h, w), dtype=dtype)
        off = 0
        for name, x in zip(cfg.channels, xs):
            c = x.shape[2]
            log = name in _LOG_CHANNELS
            if cfg.per_sample:
                dst = f[:, :, off : off + c]
                if log and not x.requires_grad:
                    dst.copy_(x)
                    sgn = torch.sign(dst)
                    dst.abs_().log1p_().mul_(sgn)  # signed_log1p in place
                else:
                    dst.copy_(signed_log1p(x) if log else x)
            else:
                # Per-pixel mean and population variance (0 at 1 spp rather than NaN).
                xl = (signed_log1p(x) if log else x).to(dtype)
                mean = xl.mean(dim=1, keepdim=True)
                f[:, :, off : off + c] = mean
                f[:, :, n_f + off : n_f + off + c] = (xl - mean).square().mean(dim=1, keepdim=True)
            off += c
        if not cfg.per_sample:
            radiance = radiance.mean(dim=1, keepdim=True)
        scene = batch.get("scene_features")
        if scene is None:
            scene = f.new_zeros(b, n_g)
        g = signed_log1p(scene.to(f.dtype))
        f[:, :, n_out:] = g[:, None, :, None, None]
        return f, radiance

    def embed(self, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Algorithm 1's loop: ``f`` (B, S, F, H, W) -> (E_n (B, S, D, H, W), C_n (B, D, H, W))."""
        e = self.embed0(f)
        ctx = f.new_zeros(0)  # replaced by the first step (steps >= 1)
        for unet, fc in zip(self.unets, self.embeds):
            ctx = unet(e.mean(dim=1))  # mean over samples: permutation invariant, any S
            e = fc(e, ctx)
        return e, ctx

    def kernel_logits(self, f: torch.Tensor) -> torch.Tensor:
        """Algorithm 1 up to the kernel: ``f`` (B, S, F, H, W) -> logits (B, S, K*K, H, W)."""
        e, ctx = self.embed(f)
        return self.kernel(e, ctx)

    def _splat_chunked(self, e: torch.Tensor, ctx: torch.Tensor, radiance: torch.Tensor, chunk: int) -> torch.Tensor:
        """Eq. 1 with kernels generated ``chunk`` samples at a time (same result as all at once)."""
        k = self.config.kernel_size
        s = e.shape[1]
        plane = None
        with torch.no_grad():  # pass 1: max logit landing on each pixel, over all samples
            for s0 in range(0, s, chunk):
                plane = destination_max(self.kernel(e[:, s0 : s0 + chunk], ctx), k, plane=plane)
        acc = SplatAccumulator()
        for s0 in range(0, s, chunk):
            logits = self.kernel(e[:, s0 : s0 + chunk], ctx)
            acc.add(radiance[:, s0 : s0 + chunk], per_destination_exp(logits, k, plane, inplace=True))
        return acc.normalized(self.config.eps)

    def _band_rows(self, b: int, s: int, w: int, itemsize: int) -> int:
        """Rows per band so one band's largest per-sample tensor fits ``kernel_budget_mb``."""
        cfg = self.config
        widest = max(cfg.kernel_size**2, cfg.fc_width, cfg.embed_width)
        per_row = b * s * widest * w * itemsize
        return max(1, (cfg.kernel_budget_mb << 20) // per_row)

    @torch.no_grad()
    def _forward_banded(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Inference: Algorithm 1 with every per-sample network run one band of rows at a time.

        The per-sample networks are 1x1 convolutions, so a band's output depends on that band's
        input only: the embeddings are updated in place band by band (one copy of E exists), and
        kernels exist for one band at a time. Only the U-Nets see the whole (per-pixel) image.
        """
        cfg = self.config
        # Built here so that ``del f`` below frees it (a caller's reference would keep it alive).
        f, radiance = self.features(batch)
        k, r = cfg.kernel_size, cfg.kernel_size // 2
        b, s, _, h, w = f.shape
        d = cfg.embed_width
        rows = self._band_rows(b, s, w, f.element_size())
        bands = [(y0, min(h, y0 + rows)) for y0 in range(0, h, rows)]
        e = f.new_empty((b, s, d, h, w))
        for y0, y1 in bands:
            e[..., y0:y1, :] = self.embed0(f[..., y0:y1, :])
        del f
        ctx = e.new_zeros(0)
        for unet, fc in zip(self.unets, self.embeds):
            ctx = unet(e.mean(dim=1))
            for y0, y1 in bands:
                e[..., y0:y1, :] = fc(e[..., y0:y1, :], ctx[..., y0:y1, :])
        radiance = radiance.to(e.dtype)
        if cfg.splat:

            def band_logits(y0: int, y1: int) -> torch.Tensor:
                # .to: bfloat16 under autocast; the splat accumulates in the embeddings' float32.
                return self.kernel(e[..., y0:y1, :], ctx[..., y0:y1, :]).to(e.dtype)

            # One band: its logits are generated once and serve both passes. Several: each pass
            # regenerates them band by band, and never two bands' logits exist at once.
            kept = band_logits(*bands[0]) if len(bands) == 1 else None
            plane = e.new_full((b, h + 2 * r, w + 2 * r), float("-inf"))
            for y0, y1 in bands:  # pass 1: max logit landing on each pixel
                destination_max(band_logits(y0, y1) if kept is None else kept, k, plane=plane, row0=y0)
            acc = e.new_zeros((b, 4, h + 2 * r, w + 2 * r))
            for y0, y1 in bands:  # pass 2: the same logits again, exponentiated in place and splatted
                weights = per_destination_exp(
                    band_logits(y0, y1) if kept is None else kept, k, plane, row0=y0, inplace=True
                )
                splat_into_(radiance[..., y0:y1, :], weights, acc, row0=y0)
                del weights
            num, wsum = acc[:, :3, r : r + h, r : r + w], acc[:, 3:, r : r + h, r : r + w]
            return normalize_splat(num, wsum, cfg.eps)
        # Gather (Fig. 5a): sample index s is its own 1-spp image; a ones channel gives the weight
        # that fell inside the image.
        img = torch.cat([radiance, torch.ones_like(radiance[:, :, :1])], dim=2).reshape(b * s, 4, h, w)
        out = e.new_zeros((b, 4, h, w))
        for y0, y1 in bands:
            logits = self.kernel(e[..., y0:y1, :], ctx[..., y0:y1, :]).to(img.dtype)
            weights = per_pixel_exp(logits, row0=y0, height=h, inplace=True)
            got = gather_rows(img, weights.reshape(b * s, k * k, y1 - y0, w), y0)
            out[..., y0:y1, :] = got.reshape(b, s, 4, y1 - y0, w).sum(dim=1)
        return normalize_splat(out[:, :3], out[:, 3:], cfg.eps)

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Denoise: per-sample buffers -> ``(B, 3, H, W)`` linear radiance; emitter pixels (an
        albedo above 1 in any sample) are filled from their neighbours in every sample and pass through
        unfiltered (:mod:`mcdenoise.models.emitters`)."""
        emitters = batch_emitter_mask(batch, self.config.channels)
        s = self.exposure_of(batch)  # of the image as given (mcdenoise.models.exposure)
        inner = fill_emitters(batch, emitters)
        out = self._denoise(inner if s is None else scale_batch(inner, s))  # type: ignore[arg-type]
        out = pass_through(unscale(out, s), batch["radiance"], emitters)
        return consistency_clamp(out, batch["radiance"], self.config.consistency, self.config.consistency_min_spp,
                                 self.config.consistency_box)

    def _denoise(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        cfg = self.config
        if not torch.is_grad_enabled():
            return self._forward_banded(batch)
        f, radiance = self.features(batch)
        e, ctx = self.embed(f)
        radiance = radiance.to(e.dtype)
        k = cfg.kernel_size
        b, s, _, h, w = e.shape
        per_sample_bytes = b * k * k * h * w * e.element_size()
        chunk = max(1, (cfg.kernel_budget_mb << 20) // per_sample_bytes)
        if cfg.splat and chunk < s:
            return self._splat_chunked(e, ctx, radiance, chunk)
        logits = self.kernel(e, ctx)
        if cfg.splat:
            num, wsum = splat(radiance, per_destination_exp(logits, k, inplace=True))
        else:
            # Each sample index is its own 1-spp image gathered with its own kernels (Fig. 5a); a
            # ones channel gives the weight that fell inside the image for the normalisation.
            weights = per_pixel_exp(logits, inplace=True)
            img = torch.cat([radiance, torch.ones_like(radiance[:, :, :1])], dim=2)
            out = gather(img.reshape(b * s, 4, h, w), weights.reshape(b * s, k * k, h, w))
            out = out.reshape(b, s, 4, h, w).sum(dim=1)
            num, wsum = out[:, :3], out[:, 3:]
        return normalize_splat(num, wsum, cfg.eps)


_PAPER = "Gharbi et al., Sample-based Monte Carlo Denoising using a Kernel-Splatting Network, SIGGRAPH 2019"


def _presets(**kw: object) -> dict:
    return {"paper": lambda: _paper(**kw), "small": lambda: _small(**kw)}


register_model(
    "sbmc",
    config_cls=SBMCConfig,
    presets=_presets(),
    paper=_PAPER + ", Sec. 3 / Algorithm 1",
    description="per-sample embeddings + U-Net context (3 steps), per-sample 21x21 kernels splatted",
)(SBMC)
register_model(
    "sbmc_gather",
    config_cls=SBMCConfig,
    presets=_presets(splat=False),
    paper=_PAPER + ", Table 2 'Gather'",
    description="SBMC ablation: per-sample kernels applied as gathers (not permutation invariant)",
)(SBMC)
register_model(
    "pixel_splat",
    config_cls=SBMCConfig,
    presets=_presets(per_sample=False),
    paper=_PAPER + ", Table 2 'PixelSplat'",
    description="SBMC ablation: per-pixel mean/variance of sample features, kernels splatted",
)(SBMC)
register_model(
    "pixel_gather",
    config_cls=SBMCConfig,
    presets=_presets(per_sample=False, splat=False),
    paper=_PAPER + ", Table 2 'PixelGather'",
    description="SBMC ablation: per-pixel mean/variance of sample features, kernels gathered",
)(SBMC)
