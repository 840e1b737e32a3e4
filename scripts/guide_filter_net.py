"""Experiment (issue 20, speed; not shipped): a small U-Net distilled from OIDN 2.5.1's albedo/normal filters.

OIDN's documented best mode for noisy guides denoises albedo and normal with OIDN first; each of
those runs costs about one OIDN ``high`` colour run at 1080p. Passing the prefiltered guides to
OIDN ``high`` as *noisy* guides keeps most of the gain at one colour run
(``scripts/guide_prefilter_probe.py``). This network was to make the prefilter cheap. Measured
(docs/models/combine.md): it loses 0.2-0.4 dB PSNR against plain OIDN on the third-party scenes,
because its albedo smooths real textures that the procedural training images do not have; the
gain of OIDN's own prefilter is in the albedo (the normal prefilter changes nothing there).

Trained by ``scripts/train_guide_filter.py``; shapes ``(B, 3, H, W)`` for albedo and normal.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F



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


def load(path: str | Path) -> GuideFilter:
    """Weights written by scripts/train_guide_filter.py -> the network in eval mode."""
    from safetensors.torch import load_file

    state = load_file(str(path))
    net = GuideFilter(int(state["e0.weight"].shape[0]), int(state["e1.0.weight"].shape[0]))
    net.load_state_dict(state)
    return net.eval()


def prefilter_guides(albedo: Any, normal: Any, net: GuideFilter) -> tuple[np.ndarray, np.ndarray]:
    """``(3, H, W)`` noisy albedo and normal -> filtered ``(3, H, W)`` float32 arrays.

    Albedo is clipped to >= 0, normals to [-1, 1] (what OIDN's guide filters give).
    """
    a = torch.from_numpy(np.ascontiguousarray(albedo, np.float32))[None]
    n = torch.from_numpy(np.ascontiguousarray(normal, np.float32))[None]
    with torch.inference_mode():
        fa, fn = net(a, n)
    return fa[0].clamp_min(0).numpy(), fn[0].clamp(-1, 1).numpy()
