"""Layer-embedding denoiser (Munkberg and Hasselgren, "Neural Denoising with Layer Embeddings", EGSR 2020).

Pipeline (Sec. 3, Appendix A): per-sample features -> sample reducer (FC, 32 features) -> mean over
samples -> U-Net -> 128 context features -> sample partitioner (FC on [embedding, context], softmax
over L layers, divided by the sample count) -> per-layer sums of radiance, weight, embedding and
occupancy (Eq. 2) -> kernel generator (FC on [layer embedding, context], 17x17 logits per layer) ->
each layer's radiance, weight and occupancy splatted with the layer's kernel (Eq. 3) -> front-to-back
alpha compositing (Eq. 4-5) or the weighted sum (Eq. 6).

``layer_optimized`` (Sec. 6) replaces the 17x17 kernel by a 3-level hierarchy of 5x5 kernels: the
layer buffers are average-pooled to 1/2 and 1/4 resolution, each level has its own kernel generator
fed with the pooled layer embeddings and the U-Net decoder features at that resolution, every level
is filtered and composited on its own, and the composited levels are upsampled and summed with
trainable weights (Eq. 10).

Emitter pixels (an albedo above 1 in any sample: lights and sky as Cycles writes them) read albedo
1 in the features, their colour is filled from their neighbours in every sample, and they pass
through unfiltered (:mod:`mcdenoise.models.emitters`); the kernels are
normalised, so elsewhere the output stays a convex combination of input radiance by design.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import nn

from mcdenoise.data.channels import SCENE_FEATURES, num_components
from mcdenoise.models.blocks import FCStack, UNet, signed_log1p
from mcdenoise.models.layer_config import (  # noqa: F401  (LAYER_CHANNELS, LayerConfig re-exported)
    LAYER_CHANNELS,
    LayerConfig,
    _paper_layer,
    _paper_optimized,
    _paper_timed_optimized,
    _medium_layer,
    _small_layer,
    _small_optimized,
)
from mcdenoise.models.base import Denoiser, register_model
from mcdenoise.models.emitters import ALBEDO_CHANNELS, as_reflectance, batch_emitter_mask, fill_emitters, pass_through
from mcdenoise.models.consistency import check_consistency, consistency_clamp
from mcdenoise.models.exposure import check_key, scale_batch, unscale
from mcdenoise.ops.composite import composite_layers, gather_layer_sums, splat_layer_sums
from mcdenoise.ops.multiscale import build_pyramid, combine_levels

__all__ = ["LayerConfig", "LayerDenoiser", "LAYER_CHANNELS", "shifted_samples"]


_LOG_CHANNELS = frozenset({"radiance", "diffuse", "specular", "depth", "depth_diffuse"})
_AP = SCENE_FEATURES.index("aperture_radius")
#: Elements of one band's largest tensor in the row-banded inference path: a band's kernel logits
#: (B, L, K*K, rows, W), or a band's per-sample features (B, S, C, rows, W). 2^26 float32 = 256 MB:
#: large enough that the kernels' row halo (K - 1 rows of zero weights) costs little splat time.
_BAND_ELEMS = 1 << 26
#: Largest reducer output (B, S, E, H, W) kept between the two banded passes instead of
#: recomputed (1080p at 8 spp with E = 8: 0.53 GB; at 32 spp and above it is recomputed).
_KEEP_BYTES = 1 << 30
_FOCUS = SCENE_FEATURES.index("focus_distance")



def shifted_samples(radiance: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """``radiance`` (B, S, 3, H, W) moved so that its mean over samples is ``mean`` (B, 3, H, W): each
    sample keeps its deviation from the samples' own mean (``LayerConfig.passes``)."""
    return radiance - radiance.mean(dim=1, keepdim=True) + mean.unsqueeze(1).to(radiance.dtype)


def _sample_weighted_sum(w: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``einsum("bslhw,bschw->blchw", w, x)`` as S x L multiply-adds of whole images: w (B, S, L,
    H, W), x (B, S, C, H, W) -> (B, L, C, H, W). Inference only. einsum lowers this to a bmm
    batched over pixels (2x32 @ 32x8 matrices), and on the row-band slices of the banded path it
    copied every pixel's matrices one by one (65k clones per band: 32 spp cost 5-8x 16 spp)."""
    b, s, nl = w.shape[:3]
    out = x.new_zeros((b, nl, x.shape[2], *x.shape[-2:]))
    for layer in range(nl):
        acc = out[:, layer]
        for i in range(s):
            acc.addcmul_(x[:, i], w[:, i, layer : layer + 1])
    return out


class LayerDenoiser(Denoiser):
    """Sample-partitioning layer denoiser.

    Input: per-sample channels ``(B, S, C, H, W)`` for each name in ``config.channels`` and
    ``scene_features`` ``(B, 5)``. Output: linear HDR radiance ``(B, 3, H, W)``. Any S >= 1, H, W.
    """

    input_kind = "samples"

    def __init__(self, config: LayerConfig) -> None:
        super().__init__(config)
        cfg = config
        if "radiance" not in cfg.channels:
            raise ValueError("the layer denoiser needs the 'radiance' channel")
        if cfg.circle_of_confusion and "depth" not in cfg.channels:
            raise ValueError("circle_of_confusion needs the 'depth' channel")
        if cfg.layers < 1:
            raise ValueError(f"layers must be >= 1, got {cfg.layers}")
        check_key("layer", cfg.autoexposure)
        check_consistency("layer", cfg.consistency, cfg.consistency_min_spp, cfg.consistency_box)
        if cfg.compositing not in ("alpha", "weighted"):
            raise ValueError(f"compositing must be 'alpha' or 'weighted', got {cfg.compositing!r}")
        if cfg.kernel_size % 2 != 1:
            raise ValueError(f"kernel_size must be odd, got {cfg.kernel_size}")
        if cfg.passes < 1:
            raise ValueError(f"passes must be >= 1, got {cfg.passes}")
        n_in = sum(num_components(c) for c in cfg.channels) + int(cfg.circle_of_confusion)
        self.input_features = n_in
        e = cfg.embed_width
        self.reducer = FCStack(n_in, [e] * cfg.reducer_layers)
        self.unet = UNet(e, cfg.context_width, cfg.unet_encoder, cfg.unet_bottleneck, cfg.unet_decoder)
        self.partitioner = FCStack(
            e, list(cfg.partitioner_widths) + [cfg.layers], context_channels=cfg.context_width, last_activation=False
        )
        k2 = cfg.kernel_size**2
        if not cfg.hierarchical:
            self.kernel_gen = FCStack(
                e, list(cfg.kernel_widths) + [k2], context_channels=cfg.context_width, last_activation=False
            )
        else:
            # Level i reads the U-Net decoder level at 1/2^i resolution, so the U-Net needs >= levels.
            if cfg.levels < 1 or cfg.levels > len(cfg.unet_decoder):
                raise ValueError(f"levels must be in 1..{len(cfg.unet_decoder)} (U-Net depth), got {cfg.levels}")
            # Level 0 reads the U-Net output; coarser levels read the decoder level at their scale.
            ctx_widths = [cfg.context_width] + [self.unet.decoder_channels[-1 - i] for i in range(1, cfg.levels)]
            # Level 0's generator also predicts the Eq. 10 level weights (Sec. 6), hence + levels.
            self.kernel_gens = nn.ModuleList(
                FCStack(e, list(cfg.kernel_widths) + [k2 + (cfg.levels if i == 0 else 0)],
                        context_channels=c, last_activation=False)
                for i, c in enumerate(ctx_widths)
            )

    def required_channels(self) -> list[str]:
        return list(self.config.channels)

    def features(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """``(f (B, S, F, H, W), radiance (B, S, 3, H, W))``: log-compressed HDR channels and
        depth, other channels as stored, plus the circle of confusion
        ``log(1 + a |1 - f / d|)`` (aperture radius ``a``, focus distance ``f``, depth ``d``; ``a``
        on a miss), a unit-free stand-in for the paper's per-sample CoC.
        """
        cfg = self.config
        parts = []
        for name in cfg.channels:
            x = batch[name]
            if x.dim() != 5:
                raise ValueError(f"layer: expects per-sample '{name}' of shape (B, S, C, H, W), got {tuple(x.shape)}")
            if name in ALBEDO_CHANNELS:
                x = as_reflectance(x)
            parts.append(signed_log1p(x) if name in _LOG_CHANNELS else x)
        if cfg.circle_of_confusion:
            d = batch["depth"]
            b = d.shape[0]
            scene = batch.get("scene_features")
            if scene is None:
                scene = d.new_zeros(b, len(SCENE_FEATURES))
            scene = scene.to(d.dtype)
            ap = scene[:, _AP].abs().view(b, 1, 1, 1, 1)
            focus = scene[:, _FOCUS].view(b, 1, 1, 1, 1)
            hit = d > 0
            ratio = torch.where(hit, focus / torch.where(hit, d, torch.ones_like(d)), torch.zeros_like(d))
            parts.append(torch.log1p(ap * (1 - ratio).abs()))
        return torch.cat(parts, dim=2), batch["radiance"]

    # -- Eq. 2: partition samples into layers ----------------------------------------------------

    def partition(
        self, e: torch.Tensor, ctx: torch.Tensor, radiance: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Sample embeddings ``e`` (B, S, E, H, W), context (B, Cc, H, W), radiance (B, S, 3, H, W)
        -> per-layer radiance (B, L, 3, H, W), weight (B, L, 1, H, W), occupancy (B, L, 1, H, W),
        embedding (B, L, E, H, W), all sums over samples (Appendix A, lines 9-17)."""
        s = e.shape[1]
        w = torch.softmax(self.partitioner(e, ctx), dim=2) / s  # (B, S, L, H, W)
        if torch.is_grad_enabled():
            l_rad = torch.einsum("bslhw,bschw->blchw", w, radiance)
            l_emb = torch.einsum("bslhw,bschw->blchw", w, e)
        else:
            l_rad, l_emb = _sample_weighted_sum(w, radiance), _sample_weighted_sum(w, e)
        l_w = w.sum(dim=1).unsqueeze(2)  # (B, L, 1, H, W)
        # A sample in layer k makes layers 0..k "see through" to it: n_j = sum_{k >= j} w_k.
        l_n = l_w.flip(1).cumsum(1).flip(1)
        return l_rad, l_w, l_n, l_emb

    def _filter(
        self,
        logits: torch.Tensor | Callable[[int, int], torch.Tensor],
        l_rad: torch.Tensor,
        l_w: torch.Tensor,
        l_n: torch.Tensor,
        extra: int = 0,
    ) -> tuple[torch.Tensor, torch.Tensor] | torch.Tensor:
        """Eq. 3 then Eq. 4-6 at one resolution (:mod:`mcdenoise.ops.composite`).

        ``logits``: the kernel generator's output (B, L, K*K + extra, h, w), or a function
        ``(y0, y1) -> `` its rows ``y0:y1``, called band by band without autograd so that no
        kernel-sized tensor of the whole image exists (at 1080p, 17x17 and L = 2: 4.8 GB each).
        Layer sums ``l_rad`` (B, L, 3, h, w), ``l_w`` and ``l_n`` (B, L, 1, h, w). Returns the
        composited (B, 3, h, w), and with ``extra`` > 0 also layer 0's extra output channels
        (B, extra, h, w) (the Eq. 10 level weights).
        """
        cfg = self.config
        b, nl, _, h, w = l_rad.shape
        kk = cfg.kernel_size**2
        gen = logits if callable(logits) else (lambda y0, y1: logits[..., y0:y1, :])
        weighted = cfg.compositing == "weighted"
        # Layer 0's extra channels per band start row; a band generated twice (banded path)
        # overwrites its first copy. Copies, so that no band's full logits stay referenced.
        extras: dict[int, torch.Tensor] = {}

        def kernel_logits(y0: int, y1: int) -> torch.Tensor:
            lg = gen(y0, y1)
            if extra:
                extras[y0] = lg[:, 0, kk:].clone()
            return lg[:, :, :kk]

        if cfg.splat:
            # Autograd keeps every band's weights anyway, so bands would only add recomputation.
            rows = h if torch.is_grad_enabled() else max(1, min(h, _BAND_ELEMS // (b * nl * (kk + extra) * w)))
            sums = splat_layer_sums(kernel_logits, l_rad, l_w, l_n, cfg.kernel_size, weighted=weighted, band_rows=rows)
        else:
            sums = gather_layer_sums(kernel_logits(0, h), l_rad, l_w, l_n, cfg.kernel_size, weighted=weighted)
        out = composite_layers(*sums, weighted=weighted)
        if not extra:
            return out
        return out, torch.cat([extras[y0] for y0 in sorted(extras)], dim=-2)

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Denoise: per-sample buffers -> ``(B, 3, H, W)`` linear radiance."""
        cfg = self.config
        emitters = batch_emitter_mask(batch, cfg.channels)
        s = self.exposure_of(batch)  # of the image as given (mcdenoise.models.exposure)

        def prepared(b: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
            inner = fill_emitters(b, emitters)
            return inner if s is None else scale_batch(inner, s)  # type: ignore[arg-type]

        inner = prepared(batch)
        out: torch.Tensor | None = None
        for _ in range(cfg.passes):
            # Later passes: the context reads the samples moved to the previous output (LayerConfig.passes).
            ctx_batch = None if out is None else prepared({**batch, "radiance": shifted_samples(batch["radiance"], out)})
            out = pass_through(unscale(self._denoise(inner, ctx_batch), s), batch["radiance"], emitters)
            out = consistency_clamp(out, batch["radiance"], cfg.consistency, cfg.consistency_min_spp, cfg.consistency_box)
        assert out is not None
        return out

    def _denoise(self, batch: dict[str, torch.Tensor], ctx_batch: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
        """``batch`` at the exposure scale -> (B, 3, H, W); the context from ``ctx_batch``'s samples when given."""
        cfg = self.config
        ctx, decoded, (l_rad, l_w, l_n, l_emb) = self._layer_sums(batch, ctx_batch)
        if not cfg.hierarchical:

            def logits(y0: int, y1: int, l_emb: torch.Tensor = l_emb, ctx: torch.Tensor = ctx) -> torch.Tensor:
                l_emb, ctx = l_emb[..., y0:y1, :], ctx[..., y0:y1, :]  # rows y0:y1 only
                return self.kernel_gen(l_emb, ctx)

            return self._filter(logits, l_rad, l_w, l_n)  # type: ignore[return-value]
        return self._forward_hierarchical(ctx, decoded, l_rad, l_w, l_n, l_emb)

    def _layer_sums(
        self, batch: dict[str, torch.Tensor], ctx_batch: dict[str, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, list[torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]]:
        """Per-sample networks, U-Net and Eq. 2: ``(context (B, Cc, H, W), U-Net decoder features
        (hierarchical only, else []), (l_rad, l_w, l_n, l_emb))`` as :meth:`partition` returns.

        Without autograd and on images whose per-sample tensors exceed ``_BAND_ELEMS``, the
        per-sample work runs in row bands, twice (once for the mean embedding the U-Net needs,
        once for the partition, which needs the U-Net's context): no (B, S, C, H, W) tensor
        besides the inputs then exists (at 1080p, 8 spp: 2.1 GB each, 8.5 GB at 32 spp), for
        twice the per-sample compute. With ``ctx_batch`` (same shapes), the U-Net reads the mean
        embedding of its samples instead of ``batch``'s.
        """
        cfg = self.config
        b, s, _, h, w = batch["radiance"].shape
        widest = max(self.input_features, cfg.embed_width, *cfg.partitioner_widths)
        # Two such tensors live at once in the reducer and partitioner (a layer's input and output).
        rows = h if torch.is_grad_enabled() else max(1, min(h, _BAND_ELEMS // (2 * b * s * widest * w)))
        if rows >= h:
            f, radiance = self.features(batch)
            e = self.reducer(f)
            radiance = radiance.to(e.dtype)
            src = e if ctx_batch is None else self.reducer(self.features(ctx_batch)[0])
            ctx, decoded = self._unet(src.mean(dim=1))
            return ctx, decoded, self.partition(e, ctx, radiance)

        def band(y0: int, y1: int, of: dict[str, torch.Tensor] = batch) -> dict[str, torch.Tensor]:
            return {n: (v[..., y0:y1, :] if v.dim() == 5 else v) for n, v in of.items()}

        # The reducer's embeddings (E channels, fewer than the F input features) are kept between
        # the two passes when they fit _KEEP_BYTES, so the second pass does not recompute the
        # features and the reducer: recomputing doubled the per-sample cost exactly when the
        # bands started (32 spp at 256x256 took 6-8x the 16-spp time, not 2x).
        e_bytes = b * s * cfg.embed_width * h * w * batch["radiance"].element_size()
        kept = batch["radiance"].new_empty((b, s, cfg.embed_width, h, w)) if e_bytes <= _KEEP_BYTES else None
        mean = None
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            if kept is not None or ctx_batch is None:
                e = self.reducer(self.features(band(y0, y1))[0])
                if kept is not None:
                    kept[..., y0:y1, :] = e
            if ctx_batch is not None:
                e = self.reducer(self.features(band(y0, y1, ctx_batch))[0])
            e = e.mean(dim=1)
            if mean is None:
                mean = e.new_empty(b, e.shape[1], h, w)
            mean[..., y0:y1, :] = e
        assert mean is not None
        ctx, decoded = self._unet(mean)
        sums: list[torch.Tensor] = []
        for y0 in range(0, h, rows):
            y1 = min(h, y0 + rows)
            if kept is not None:
                e, radiance = kept[..., y0:y1, :], batch["radiance"][..., y0:y1, :]
            else:
                f, radiance = self.features(band(y0, y1))
                e = self.reducer(f)
            parts = self.partition(e, ctx[..., y0:y1, :], radiance.to(e.dtype))
            if not sums:
                sums = [p.new_empty(*p.shape[:-2], h, w) for p in parts]
            for out, p in zip(sums, parts):
                out[..., y0:y1, :] = p
        return ctx, decoded, tuple(sums)  # type: ignore[return-value]

    def _unet(self, mean: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor]]:
        # Only the hierarchy needs the decoder features (the finest is a full-resolution tensor).
        if self.config.hierarchical:
            return self.unet(mean, return_decoder=True)  # type: ignore[return-value]
        return self.unet(mean), []  # type: ignore[return-value]

    def _forward_hierarchical(
        self,
        ctx: torch.Tensor,
        decoded: list[torch.Tensor],
        l_rad: torch.Tensor,
        l_w: torch.Tensor,
        l_n: torch.Tensor,
        l_emb: torch.Tensor,
    ) -> torch.Tensor:
        """Sec. 6: filter and composite each pyramid level on its own (G_i), then Eq. 10."""
        cfg = self.config
        b, nl = l_rad.shape[:2]
        # Box-downsampled sums keep every ratio of Eq. 4 meaningful (a mean of sums is a scaled sum).
        stacked = torch.cat([l_rad, l_w, l_n, l_emb], dim=2).flatten(1, 2)
        pyramid = build_pyramid(stacked, cfg.levels)
        ctxs = [ctx] + [decoded[-1 - i] for i in range(1, cfg.levels)]
        levels = []
        lam = None
        for i, (buf, ctx_i) in enumerate(zip(pyramid, ctxs)):
            hh, ww = buf.shape[-2:]
            buf = buf.reshape(b, nl, -1, hh, ww)
            rad, lw, ln, emb_i = buf[:, :, :3], buf[:, :, 3:4], buf[:, :, 4:5], buf[:, :, 5:]

            def logits(y0: int, y1: int, i: int = i, emb_i: torch.Tensor = emb_i, ctx_i: torch.Tensor = ctx_i) -> torch.Tensor:
                emb, c = emb_i[..., y0:y1, :], ctx_i[..., y0:y1, :]
                return self.kernel_gens[i](emb, c)

            if i == 0:
                # The first layer's level-0 generator also outputs the per-pixel level weights.
                g, lam_logits = self._filter(logits, rad, lw, ln, extra=cfg.levels)  # type: ignore[misc]
                lam = torch.softmax(lam_logits, dim=1)
            else:
                g = self._filter(logits, rad, lw, ln)
            levels.append(g)
        assert lam is not None
        return combine_levels(levels, lam)


_PAPER = "Munkberg and Hasselgren, Neural Denoising with Layer Embeddings, EGSR 2020"

register_model(
    "layer",
    config_cls=LayerConfig,
    presets={"paper": _paper_layer, "medium": _medium_layer, "small": _small_layer,
             "medium_2pass": lambda: _medium_layer(passes=2)},  # LayerConfig.passes: layer-medium run twice
    paper=_PAPER + ", Sec. 3 / Appendix A-B",
    description="samples partitioned into 2 layers, 17x17 splat kernel per layer, front-to-back alpha compositing",
)(LayerDenoiser)
register_model(
    "layer_weighted",
    config_cls=LayerConfig,
    presets={
        "paper": lambda: _paper_layer(compositing="weighted"),
        "small": lambda: _small_layer(compositing="weighted"),
    },
    paper=_PAPER + ", Sec. 3.1 Eq. 6",
    description="layer denoiser with the weighted-sum compositing of Eq. 6 instead of alpha blending",
)(LayerDenoiser)
register_model(
    "layer_optimized",
    config_cls=LayerConfig,
    presets={"paper": _paper_optimized, "paper_timed": _paper_timed_optimized, "small": _small_optimized},
    paper=_PAPER + ", Sec. 6",
    description="layer denoiser with 3-level hierarchical 5x5 kernels and reduced widths",
)(LayerDenoiser)
