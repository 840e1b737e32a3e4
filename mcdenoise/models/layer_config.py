"""Configuration and presets of the layer-embedding denoisers (``layer``, ``layer_weighted``,
``layer_optimized``; the model is :mod:`mcdenoise.models.layer`). Split from ``layer.py`` by size.
"""

from __future__ import annotations

from dataclasses import dataclass

from mcdenoise.models.consistency import ConsistencyOptions

__all__ = ["LayerConfig", "LAYER_CHANNELS"]

#: Per-sample channels (Sec. 3 "Per-sample Processing": normal, depth, albedo, specular, roughness,
#: lens position, time; motion vectors are per pixel in our format, so sub-pixel position stands in).
#: With the derived circle of confusion this makes 20 floats per sample, as in the paper.
LAYER_CHANNELS: tuple[str, ...] = (
    "radiance",
    "specular",
    "albedo",
    "normal",
    "depth",
    "roughness",
    "lens",
    "time",
    "subpixel",
)


@dataclass
class LayerConfig(ConsistencyOptions):
    """Configuration of :class:`LayerDenoiser` (``layer``, ``layer_weighted``, ``layer_optimized``)."""

    channels: tuple[str, ...] = LAYER_CHANNELS
    """Per-sample vocabulary channels fed to the sample reducer; must include ``radiance``."""
    circle_of_confusion: bool = True
    """Append a per-sample circle-of-confusion feature computed from ``depth`` and the scene's
    aperture and focus distance (needs ``depth`` in ``channels``)."""
    layers: int = 2
    """L, number of layers samples are partitioned into (Sec. 5: 2)."""
    embed_width: int = 32
    """Width of the sample embeddings (Appendix B: 32)."""
    reducer_layers: int = 3
    """Fully connected layers of the sample reducer (Appendix B: 3)."""
    context_width: int = 128
    """Context features produced by the U-Net (Appendix B: 128)."""
    unet_encoder: tuple[tuple[int, ...], ...] = ((64, 64), (128,), (256,), (512,), (512,))
    """Conv widths of each U-Net encoder level, finest first. UNVERIFIED: the paper's Fig. 3 (the
    U-Net layout) is lost in our copy of the paper; these widths are our guess, and they are very
    likely too wide (this U-Net holds 17.9M of the model's 18.0M parameters and the Sec. 6
    timing cannot be met with it; see docs/models/layer.md and the ``paper_timed`` preset)."""
    unet_bottleneck: tuple[int, ...] = (512,)
    """Conv widths at the U-Net's coarsest level. UNVERIFIED (Fig. 3 lost; see ``unet_encoder``)."""
    unet_decoder: tuple[tuple[int, ...], ...] = ((512, 512), (256, 256), (128, 128), (128, 128), (128, 128))
    """Conv widths of each U-Net decoder level, coarsest first. UNVERIFIED (Fig. 3 lost; see
    ``unet_encoder``)."""
    partitioner_widths: tuple[int, ...] = (32, 16)
    """Hidden widths of the sample partitioner; its last layer outputs L logits (Appendix B)."""
    kernel_widths: tuple[int, ...] = (128, 128)
    """Hidden widths of the kernel generator; its last layer outputs K*K logits (Appendix B)."""
    kernel_size: int = 17
    """Side of each layer's kernel (17 in the paper); 5 for the hierarchical variant."""
    compositing: str = "alpha"
    """"alpha": occupancy-tracked front-to-back compositing (Eq. 2-5). "weighted": Eq. 6."""
    splat: bool = True
    """Apply layer kernels as splats (the paper, following SBMC) or as gathers."""
    hierarchical: bool = False
    """Sec. 6: ``levels`` levels of ``kernel_size`` kernels at full, 1/2, 1/4... resolution (Eq. 10)."""
    levels: int = 3
    """Number of levels of the hierarchical variant."""
    autoexposure: float | None = None
    """Key of the image-level autoexposure (:mod:`mcdenoise.models.exposure`; not in the paper):
    the radiance is scaled to it before the network and back after, so the output follows
    exposure exactly. None: the network sees the radiance as given."""
    consistency: float | None = None
    """Clamp each output pixel to this many (shrunk) standard errors around the mean of its own
    samples (:mod:`mcdenoise.models.consistency`; not in the paper). Set after training, on held-out
    images; None: no clamp."""
    passes: int = 1
    """Runs of the network; each run after the first reads its context (the U-Net's input, the mean
    of the sample embeddings) from the samples moved so that their mean is the previous run's
    output, each sample keeping its deviation from the samples' mean
    (:func:`~mcdenoise.models.layer.shifted_samples`); the kernels still filter the samples as given.
    Not in the paper. Why: campaign 36 (``scripts/kernel_noise_probe.py``) found that the context
    decides layer-medium's 4-spp bias on scenes we did not make: read from 16 samples while the
    kernels filter 4, the third-party relMSE fell by a third (0.140 to 0.093). A clean mean with
    the samples' own spread gives the context the structure of the first pass's output and the
    noise level of the samples: with no training, 0.140 to 0.095 there (0.94x per image), but 1.32x
    per image on our own held-out images, where a few explode. So untrained it is no option; it is the
    start of a training leg (preset ``medium_2pass``, initialised from layer-medium's weights)."""


def _paper_layer(**kw: object) -> LayerConfig:
    return LayerConfig(**kw)  # type: ignore[arg-type]


def _paper_optimized(**kw: object) -> LayerConfig:
    # Sec. 6: kernel generator 128 -> 32 features, U-Net's first two encoder convs at 32 and last
    # four decoder convs at 64, 3 levels of 5x5 kernels.
    return LayerConfig(
        kernel_widths=(32, 32),
        unet_encoder=((32, 32), (128,), (256,), (512,), (512,)),
        unet_decoder=((512, 512), (256, 256), (128, 128), (64, 64), (64, 64)),
        kernel_size=5,
        hierarchical=True,
        **kw,  # type: ignore[arg-type]
    )


def _paper_timed_optimized(**kw: object) -> LayerConfig:
    # Sec. 6 with a U-Net sized to the paper's Table 3: 18.8 ms for the U-Net at 1920x1080 on an
    # RTX 2080 Ti. At a realistic 10-15 TFLOP/s that is 0.19-0.28 TFLOP per frame, 91-136
    # kFLOP per pixel; this U-Net costs 113 kFLOP/pixel (0.234 TFLOP/frame, 18.8 ms at 12.4
    # TFLOP/s), where the unverified ``paper`` widths cost 685 (1.42 TFLOP). Our own choice of
    # widths, not the paper's (Fig. 3 is lost): 5 levels, one conv per level, 32 wide at full
    # and half resolution on both sides (the paper's "first two encoder convs at 32"), doubling
    # towards 128 at the coarsest level. Derivation in docs/models/layer.md.
    return LayerConfig(
        kernel_widths=(32, 32),
        unet_encoder=((32,), (48,), (64,), (96,), (128,)),
        unet_bottleneck=(128,),
        unet_decoder=((128,), (96,), (64,), (32,), (32,)),
        kernel_size=5,
        hierarchical=True,
        **kw,  # type: ignore[arg-type]
    )


def _small_common() -> dict:
    return dict(
        embed_width=8,
        reducer_layers=2,
        context_width=16,
        unet_encoder=((16,), (24,)),
        unet_bottleneck=(32,),
        unet_decoder=((24,), (16,)),
        partitioner_widths=(8,),
    )


def _small_layer(**kw: object) -> LayerConfig:
    return LayerConfig(**_small_common(), kernel_widths=(16,), kernel_size=9, **kw)  # type: ignore[arg-type]


def _small_optimized(**kw: object) -> LayerConfig:
    common = _small_common()
    # Three U-Net levels so that every pyramid level has decoder features at its resolution.
    common.update(unet_encoder=((8,), (16,), (24,)), unet_bottleneck=(32,), unet_decoder=((24,), (16,), (16,)))
    return LayerConfig(**common, kernel_widths=(8,), kernel_size=5, hierarchical=True, **kw)  # type: ignore[arg-type]


def _medium_layer(**kw: object) -> LayerConfig:
    # Sized for a GPU campaign (campaign 13: ~1M parameters, 3000 steps of 16 128x128 crops on an
    # H100 in 5 minutes): the paper's embedding width, reducer depth, partitioner and 17x17 kernels,
    # with a 4-level U-Net one conv per level, 32-128 wide (the paper's 18M-parameter U-Net widths
    # are unverified and far beyond what CPU inference can afford; docs/models/layer.md).
    return LayerConfig(
        embed_width=32,
        reducer_layers=3,
        context_width=64,
        unet_encoder=((32,), (64,), (96,), (128,)),
        unet_bottleneck=(128,),
        unet_decoder=((128,), (96,), (64,), (32,)),
        partitioner_widths=(32, 16),
        kernel_widths=(64, 64),
        kernel_size=17,
        **kw,  # type: ignore[arg-type]
    )

