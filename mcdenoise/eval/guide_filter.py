"""A cheap prefilter for OIDN's guides: a small network distilled from OIDN 2.5.1's own guide filters.

OIDN's documented best mode for noisy albedo and normal is to denoise each guide with OIDN first.
Each of those two runs costs about one OIDN ``high`` colour run at 1080p (measured, see
docs/models/combine.md), which puts the whole path at 3x OIDN before any combiner. The same guides
passed to OIDN ``high`` as *noisy* guides (no ``cleanAux``) already give most of the gain and keep
OIDN's robustness (``scripts/guide_prefilter_probe.py``: 0.76x plain OIDN's relMSE on the
third-party scenes at 8 spp, never more than 1% worse on one of them). This module makes that
prefilter cheap: a U-Net of 8 and 16 channels (4.5k multiply-adds a pixel) maps the noisy guides to
what OIDN's guide filters make of them.

Shapes: ``albedo``, ``normal`` are ``(B, 3, H, W)``; the network reads both and writes both.
Weights: ``mcdenoise/models/shipped/guide_filter.safetensors`` (trained by
``scripts/train_guide_filter.py``; recipe in docs/TRAINING.md). Like OIDN, it is a fixed function
of its inputs once shipped: the derived channel ``oidn_gf`` names the weights' digest in its cache.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

__all__ = ["GuideFilter", "WEIGHTS", "guide_filter", "prefilter_guides", "weights_digest"]

#: The shipped weights (not a denoiser: ``shipped()`` lists ``name-preset`` files only).
WEIGHTS = Path(__file__).resolve().parents[1] / "models" / "shipped" / "guide_filter.safetensors"


class GuideFilter(nn.Module):
    """Noisy (albedo, normal) -> filtered (albedo, normal): a 3-level U-Net with a residual output.

    Full resolution: one conv in, one conv out (``c0`` channels); half and quarter resolution
    (average pooling, bilinear upsampling, concatenated skips) carry ``c1`` channels. Padding
    replicates the border; any H, W work (padded to a multiple of 4, cropped back).
    """

    def __init__(self, c0: int = 8, c1: int = 16) -> None:
        super().__init__()
        self.c0, self.c1 = c0, c1
        conv = lambda i, o: nn.Conv2d(i, o, 3, padding=1, padding_mode="replicate")
        self.e0 = conv(6, c0)
        self.e1 = nn.Sequential(conv(c0, c1), nn.ReLU(inplace=True), conv(c1, c1), nn.ReLU(inplace=True))
        self.b = nn.Sequential(conv(c1, c1), nn.ReLU(inplace=True), conv(c1, c1), nn.ReLU(inplace=True))
        self.d1 = nn.Sequential(conv(2 * c1, c1), nn.ReLU(inplace=True))
        self.d0 = nn.Sequential(conv(c1 + c0, c0), nn.ReLU(inplace=True))
        self.out = nn.Conv2d(c0, 6, 1)
        with torch.no_grad():  # start as the identity: the residual is 0
            self.out.weight.zero_()
            self.out.bias.zero_()

    def forward(self, albedo: torch.Tensor, normal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([albedo, normal], 1)
        h, w = x.shape[-2:]
        ph, pw = (-h) % 4, (-w) % 4
        xp = F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x
        f0 = F.relu(self.e0(xp))
        f1 = self.e1(F.avg_pool2d(f0, 2))
        f2 = self.b(F.avg_pool2d(f1, 2))
        u1 = self.d1(torch.cat([F.interpolate(f2, size=f1.shape[-2:], mode="bilinear", align_corners=False), f1], 1))
        u0 = self.d0(torch.cat([F.interpolate(u1, size=f0.shape[-2:], mode="bilinear", align_corners=False), f0], 1))
        y = (xp + self.out(u0))[..., :h, :w]
        return y[:, :3], y[:, 3:]


def weights_digest(path: Path = WEIGHTS) -> str:
    """First 12 hex digits of the weights file's SHA-256 (names the ``oidn_gf`` cache). Read each
    time (a few tens of KB): a file rewritten within the clock's granularity keeps its mtime."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]


@functools.lru_cache(maxsize=2)
def _load(path: str, digest: str) -> GuideFilter:
    from safetensors.torch import load_file

    state = load_file(path)
    c0, c1 = int(state["e0.weight"].shape[0]), int(state["e1.0.weight"].shape[0])
    net = GuideFilter(c0, c1)
    net.load_state_dict(state)
    return net.eval()


def guide_filter(path: Path = WEIGHTS) -> GuideFilter:
    """The shipped guide filter (loaded once per weights content)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no guide-filter weights (train them with scripts/train_guide_filter.py)")
    return _load(str(path), weights_digest(path))


def prefilter_guides(albedo: Any, normal: Any, net: GuideFilter | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(3, H, W)`` noisy albedo and normal -> filtered ``(3, H, W)`` float32 arrays.

    Albedo is clipped to >= 0, normals to [-1, 1] (what OIDN's guide filters give).
    """
    net = guide_filter() if net is None else net
    a = torch.from_numpy(np.ascontiguousarray(albedo, np.float32))[None]
    n = torch.from_numpy(np.ascontiguousarray(normal, np.float32))[None]
    with torch.inference_mode():
        fa, fn = net(a, n)
    return fa[0].clamp_min(0).numpy(), fn[0].clamp(-1, 1).numpy()
