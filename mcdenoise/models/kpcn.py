"""KPCN and DPCN (Bako, Vogels et al. 2017): per-pixel denoising of a diffuse/specular split.

Each branch (diffuse, specular; or one ``radiance`` branch for inputs without a split) is a plain
stack of ``layers`` 5x5 convolutions with ReLU between them (Sec. 4.1, 5.2). Its input is built by
:meth:`KPCN.features` from the stored buffers (Sec. 4.3, 5.1):

* the feature buffers (albedo, normal, depth) are those of the first diffuse intersection
  (``albedo_diffuse``, ``normal_diffuse``, ``depth_diffuse``), as the paper saves them (Sec. 6:
  "at the first diffuse intersection in order to handle specular regions ... e.g., glass");
  ``KPCNConfig.feature_hit = "first"`` takes the first-hit buffers for data without them;
* diffuse: irradiance ``c / (albedo + eps)``, ``eps = 0.00316``; specular and single-branch
  radiance: ``log(1 + c)``;
* x and y gradients of that colour and of normal, albedo and depth;
* the colour variance carried through the same transform to first order (Eq. 5), reduced to one
  channel by its luminance, and the normal, albedo and depth variances, one channel each; the
  ``pixel`` preset (``variance = "window"``, first-hit features) measures each variance over a 5x5
  window of the transformed feature instead, for inputs that carry no samples or variances
  (Blender's passes, pbrt, OIDN-style files);
* depth mapped by ``log(1 + depth / depth_scale)``, a fixed rule, so that a crop's features are
  the crop of the whole image's (the paper scales to [0, 1] per frame, which differs per tile).

KPCN predicts a KxK kernel per pixel (softmax over the K^2 taps, Sec. 4.2) applied to the
transformed noisy colour; DPCN predicts the transformed colour directly. The branches are
recombined with Eq. 4: ``(albedo + eps) * diffuse + exp(specular) - 1``.

Emitter pixels (an albedo above 1: lights and sky as Cycles writes them) read albedo 1 in the
features, the division and Eq. 4 alike, their colour is filled from their neighbours in what the
network and the kernels see, and they pass through unfiltered
(:mod:`mcdenoise.models.emitters`); elsewhere that rule is the identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from mcdenoise.data.channels import variance_name
from mcdenoise.models.base import Denoiser, register_model
from mcdenoise.models.emitters import as_reflectance, emitter_mask, fill_emitters, pass_through
from mcdenoise.models.consistency import ConsistencyOptions, check_consistency
from mcdenoise.models.exposure import check_key, scale_batch, unscale
from mcdenoise.models.kpcn_features import FEATURES_PER_BRANCH, kpcn_features, window_variance
from mcdenoise.ops.gather import gather, gather_rows
from mcdenoise.ops.kernels import softmax_kernel

__all__ = ["KPCNConfig", "KPCN", "apply_kernels", "kpcn_features", "window_variance", "FEATURES_PER_BRANCH"]


@dataclass
class KPCNConfig(ConsistencyOptions):
    """Configuration of one KPCN/DPCN network (both branches share it)."""

    layers: int = 9
    """Number of convolutions per branch, the last one linear (paper: L = 9)."""
    channels: int = 100
    """Width of every hidden layer (paper: 100)."""
    conv_size: int = 5
    """Spatial size of every convolution (paper: 5x5)."""
    kernel_size: int = 21
    """Side K of the predicted per-pixel filter (paper: 21); unused when ``direct``."""
    direct: bool = False
    """True: DPCN, the last layer outputs the (transformed) colour itself instead of a kernel."""
    split: bool = True
    """True: separate diffuse and specular branches (Sec. 4.3); False: one branch on ``radiance``."""
    eps: float = 0.00316
    """Added to the albedo before dividing (Sec. 4.3)."""
    feature_hit: str = "diffuse"
    """Where the albedo/normal/depth features come from: ``"diffuse"``, the first diffuse
    intersection (the paper); ``"first"``, the first intersection (data without the
    ``*_diffuse`` buffers)."""
    depth_scale: float = 1.0
    """Depth feature ``log(1 + depth / depth_scale)``, in world units: depths well above it are
    seen relatively (a step from 10 to 11 looks like one from 100 to 110)."""
    variance: str = "input"
    """Where the variance features come from: ``"input"``, the ``*_variance`` channels (variance
    of the mean from the samples, the paper); ``"window"``, the variance of each feature over a
    ``variance_window`` square around the pixel, in the feature's own domain (inputs with no
    samples and no variance: Blender, pbrt, OIDN-style files)."""
    variance_window: int = 5
    """Side of the ``"window"`` estimate (odd)."""
    autoexposure: float | None = None
    """Scale each image (crop in training) so its block-luminance geometric mean is this key
    before the network, and back after it (:mod:`mcdenoise.models.exposure`): the output no longer
    depends on the input's absolute brightness. None: the network sees the radiance as given."""
    consistency: float | None = None
    """Clamp each output pixel to this many (shrunk) standard errors around the input's pixel mean,
    where the input has per-pixel variances (:func:`mcdenoise.models.consistency.pixel_consistency_clamp`,
    applied by ``denoise`` and ``eval`` after the model; not in the paper). Set after training, on
    held-out images; None: no clamp."""

    def feature_channels(self) -> tuple[str, str, str]:
        """Names of the (albedo, normal, depth) buffers the features read."""
        if self.feature_hit == "diffuse":
            return ("albedo_diffuse", "normal_diffuse", "depth_diffuse")
        if self.feature_hit == "first":
            return ("albedo", "normal", "depth")
        raise ValueError(f"KPCNConfig.feature_hit: expected 'diffuse' or 'first', got {self.feature_hit!r}")


def _mask_out_of_image_taps(z: torch.Tensor, k: int) -> torch.Tensor:
    """(B, K*K, H, W) logits -> same with -inf wherever tap (i-r, j-r) of a pixel leaves the image.

    Built as a row term (K, H) plus a column term (K, W) broadcast into the sum, so no
    K*K x H x W mask is allocated (it would be ~1 GB at 1080p with K = 21).
    """
    b, _, h, w = z.shape
    r = k // 2
    off = torch.arange(-r, r + 1, device=z.device)
    ys = torch.arange(h, device=z.device).view(1, h) + off.view(k, 1)  # (K, H)
    xs = torch.arange(w, device=z.device).view(1, w) + off.view(k, 1)  # (K, W)
    neg = torch.tensor(float("-inf"), dtype=z.dtype, device=z.device)
    zero = torch.zeros((), dtype=z.dtype, device=z.device)
    row = torch.where((ys >= 0) & (ys < h), zero, neg).view(1, k, 1, h, 1)
    col = torch.where((xs >= 0) & (xs < w), zero, neg).view(1, 1, k, 1, w)
    return (z.view(b, k, k, h, w) + row + col).view(b, k * k, h, w)


def _mask_border_taps_(z: torch.Tensor, k: int, row0: int, height: int) -> torch.Tensor:
    """In place, the same -inf as :func:`_mask_out_of_image_taps` on a contiguous (B, K*K, h, W)
    band of rows ``row0 ..``, written only where it lands: the r columns at each side and the
    band's rows within r of the image's top or bottom (interior pixels are not touched)."""
    b, _, h, w = z.shape
    r = k // 2
    z5 = z.view(b, k, k, h, w)
    neg = float("-inf")
    for d in range(1, r + 1):  # tap offset d to the left/right/up/down reads outside within d pixels
        z5[:, :, r - d, :, : min(d, w)] = neg  # dx = -d: columns x < d
        z5[:, :, r + d, :, max(0, w - d) :] = neg  # dx = +d: columns x >= W - d
        top = max(0, min(h, d - row0))  # rows y (global row0 + y) < d
        if top:
            z5[:, r - d, :, :top] = neg
        bottom = max(0, min(h, row0 + h - (height - d)))  # rows with row0 + y >= height - d
        if bottom:
            z5[:, r + d, :, h - bottom :] = neg
    return z


def _apply_kernels_banded(color: torch.Tensor, logits: torch.Tensor, k: int, band_bytes: int = 8 << 20) -> torch.Tensor:
    """Inference form of ``gather(color, softmax(mask(logits)))``, one row band at a time.

    color (B, 3, H, W) float32; logits (B, K*K, H, W) in any dtype and memory format (a bfloat16
    channels_last trunk output is converted here band by band, in float32). Every band's mask,
    softmax and gather stay in the cache instead of streaming three K*K x H x W tensors through
    memory, and the mask touches only border pixels; equal to the whole-image path
    (tests/test_model_kpcn.py).
    """
    b, _, h, w = color.shape
    kk = k * k
    out = torch.empty_like(color)
    rows = max(1, min(h, band_bytes // max(1, b * kk * w * 4)))
    # One band buffer for every band and the softmax in place: no allocation per band.
    buf = torch.empty(b * kk * rows * w, dtype=color.dtype, device=color.device)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        zb = buf[: b * kk * (r1 - r0) * w].view(b, kk, r1 - r0, w)
        zb.copy_(logits[:, :, r0:r1])
        _mask_border_taps_(zb, k, r0, h)
        zb.sub_(zb.amax(dim=1, keepdim=True)).exp_()  # the centre tap is in the image: max finite
        # Normalise the 3-channel result, not the K*K weights: the same sum, K*K/3 fewer divisions.
        out[:, :, r0:r1] = gather_rows(color, zb, r0).div_(zb.sum(dim=1, keepdim=True))
    return out


def apply_kernels(color: torch.Tensor, logits: torch.Tensor, k: int) -> torch.Tensor:
    """(B, 3, H, W) colour filtered by per-pixel K x K softmax kernels from (B, K*K, H, W) logits.

    Taps outside the image get no weight, so the softmax renormalises over the image instead of
    blending in zero padding at the borders. With gradients off it runs
    :func:`_apply_kernels_banded` (same values, a row band at a time); with them, the
    differentiable whole-image path.
    """
    if not torch.is_grad_enabled():
        return _apply_kernels_banded(color, logits, k)
    # Under autocast the logits come out of the convolutions in bfloat16; the softmax and the
    # gather stay in the colour's precision (bfloat16 keeps 8 bits of mantissa, ~0.4% per weight).
    return gather(color, softmax_kernel(_mask_out_of_image_taps(logits.to(color.dtype), k)))


class _Branch(nn.Module):
    """L convolutions, ReLU after all but the last (Sec. 4.1)."""

    def __init__(self, config: KPCNConfig, in_ch: int, out_ch: int) -> None:
        super().__init__()
        pad = config.conv_size // 2
        layers: list[nn.Module] = []
        ch = in_ch
        for _ in range(config.layers - 1):
            layers += [nn.Conv2d(ch, config.channels, config.conv_size, padding=pad), nn.ReLU(inplace=True)]
            ch = config.channels
        layers.append(nn.Conv2d(ch, out_ch, config.conv_size, padding=pad))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class KPCN(Denoiser):
    """KPCN / DPCN, split or single-branch, chosen by :class:`KPCNConfig`."""

    input_kind = "pixels"
    #: The branches' logits may come back from a bfloat16 channels_last trunk as they are:
    #: :func:`_apply_kernels_banded` converts them a row band at a time.
    trunk_outputs_any_layout = True

    def __init__(self, config: KPCNConfig) -> None:
        super().__init__(config)
        if config.layers < 1 or config.kernel_size % 2 == 0:
            raise ValueError(f"KPCN: need layers >= 1 and an odd kernel_size, got {config}")
        if not config.depth_scale > 0:
            raise ValueError(f"KPCN: depth_scale must be > 0, got {config.depth_scale}")
        check_key("KPCN", config.autoexposure)
        check_consistency("KPCN", config.consistency, config.consistency_min_spp, config.consistency_box)
        config.feature_channels()  # refuses an unknown feature_hit now, not at the first batch
        if config.variance not in ("input", "window") or config.variance_window < 1 or config.variance_window % 2 == 0:
            raise ValueError(f"KPCN: variance must be 'input' or 'window' with an odd variance_window, got {config}")
        out_ch = 3 if config.direct else config.kernel_size**2
        names = ("diffuse", "specular") if config.split else ("radiance",)
        self.branches = nn.ModuleDict({n: _Branch(config, FEATURES_PER_BRANCH, out_ch) for n in names})

    def conv_trunks(self) -> list[str]:
        """Each branch's convolution stack (its last layer outputs the kernel logits, which the
        softmax then takes in float32)."""
        return [f"branches.{n}" for n in self.branches]

    def required_channels(self) -> list[str]:
        colors = ["diffuse", "specular"] if self.config.split else ["radiance"]
        names = colors + list(self.config.feature_channels())
        if self.config.variance == "window":
            return names
        return names + [variance_name(n) for n in names]

    def features(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Branch name -> (B, 27, H, W) network input (see module docstring)."""
        missing = [n for n in self.required_channels() if n not in batch]
        if missing:
            raise ValueError(f"{type(self).__name__}: batch lacks channels {missing}")
        return kpcn_features(batch, self.config)

    def exposure_colour(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        return batch["diffuse"] + batch["specular"] if self.config.split else batch["radiance"]

    def forward_branches(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Branch name -> (B, 3, H, W) denoised colour in the branch's transformed domain (at the
        autoexposure scale, when the config has one).

        ``diffuse`` is irradiance (divided by albedo + eps), ``specular``/``radiance`` is
        ``log(1 + c)``. Compare against :meth:`branch_targets` for the paper's per-branch L1
        pre-training; :meth:`recombine` gives the final image.
        """
        s = self.exposure_of(batch)
        return self._branches(batch if s is None else scale_batch(batch, s))

    def _branches(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        out: dict[str, torch.Tensor] = {}
        for name, x in self.features(batch).items():
            z = self.branches[name](x)
            if self.config.direct:
                out[name] = z.to(x.dtype, memory_format=torch.contiguous_format)
                continue
            out[name] = apply_kernels(x[:, :3], z, self.config.kernel_size)
        return out

    def branch_targets(self, reference: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Reference colours (B, 3, H, W) carried into each branch's domain with the noisy albedo
        (the feature albedo, as in :meth:`recombine`), at :meth:`forward_branches`' exposure."""
        s = self.exposure_of(batch)
        if s is not None:
            reference = scale_batch(reference, s)
        if self.config.split:
            albedo = as_reflectance(batch[self.config.feature_channels()[0]])
            return {
                "diffuse": reference["diffuse"] / (albedo + self.config.eps),
                "specular": torch.log1p(reference["specular"].clamp_min(0)),
            }
        return {"radiance": torch.log1p(reference["radiance"].clamp_min(0))}

    def recombine(self, branches: dict[str, torch.Tensor], batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Eq. 4: (albedo + eps) * diffuse + exp(specular) - 1 -> (B, 3, H, W) linear HDR.

        ``albedo`` is the one the features divided by (:meth:`KPCNConfig.feature_channels`), so
        the inverse is exact.
        """
        if self.config.split:
            albedo = as_reflectance(batch[self.config.feature_channels()[0]])
            return (albedo + self.config.eps) * branches["diffuse"] + torch.expm1(branches["specular"])
        return torch.expm1(branches["radiance"])

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        emitters = emitter_mask(batch[self.config.feature_channels()[0]])
        s = self.exposure_of(batch)  # of the image as given: a tile's scale is its whole image's
        inner = fill_emitters(batch, emitters)
        if s is not None:
            inner = scale_batch(inner, s)
        out = self.recombine(self._branches(inner), inner)  # type: ignore[arg-type]
        return pass_through(unscale(out, s), self.exposure_colour(batch), emitters)


_PAPER = "Bako, Vogels et al., Kernel-Predicting Convolutional Networks for Denoising Monte Carlo Renderings, SIGGRAPH 2017"


def _paper(**kw: object) -> KPCNConfig:
    return KPCNConfig(layers=9, channels=100, conv_size=5, kernel_size=21, **kw)  # type: ignore[arg-type]


def _small(**kw: object) -> KPCNConfig:
    return KPCNConfig(layers=4, channels=24, conv_size=5, kernel_size=9, **kw)  # type: ignore[arg-type]


def _pixel(**kw: object) -> KPCNConfig:
    """``small`` for inputs without samples: features at the first hit (``albedo``, ``normal``,
    ``depth``, which Blender's denoising passes give) and window variances."""
    return _small(feature_hit="first", variance="window", **kw)


@register_model(
    "kpcn",
    config_cls=KPCNConfig,
    presets={"paper": _paper, "small": _small, "pixel": _pixel},
    paper=_PAPER,
    description="diffuse/specular branches, 9 conv x 100 ch, 21x21 softmax gather kernels, Eq. 4 recombination",
)
class KPCNModel(KPCN):
    pass


@register_model(
    "dpcn",
    config_cls=KPCNConfig,
    presets={"paper": lambda: _paper(direct=True), "small": lambda: _small(direct=True)},
    paper=_PAPER,
    description="KPCN's network predicting the transformed colour directly (DPCN)",
)
class DPCNModel(KPCN):
    pass


@register_model(
    "kpcn_single",
    config_cls=KPCNConfig,
    presets={"paper": lambda: _paper(split=False), "small": lambda: _small(split=False),
             "pixel": lambda: _pixel(split=False)},
    paper=_PAPER,
    description="one KPCN branch on log(1 + radiance) for inputs without a diffuse/specular split",
)
class KPCNSingleModel(KPCN):
    pass
