"""SBMC Fig. 4: downsampling a texture with outlier samples, gather vs splat of equal capacity.

The task (Gharbi et al. 2019, Sec. 3.4): given the samples of a high-resolution texture, some of
them replaced by high-energy outliers, produce the anti-aliased downsampled image, i.e. the clean
texture blurred with a Gaussian and subsampled. Without outliers both networks would only need to
predict that Gaussian; with outliers, a gather kernel must place a zero on every outlier among its
neighbours (a combinatorial set of Dirac holes), whereas a splat kernel only has to switch off its
own sample.

Our set-up, chosen so that the two networks differ in nothing but the direction of the kernel:

* samples live on the high-resolution grid (one sample per texel, ``factor x factor`` samples per
  output pixel); textures are procedural (gratings, checkers, discs, value noise), so nothing is
  downloaded;
* both networks are the paper's limited-capacity predictor: 3 conv layers x 32 channels (3x3,
  leaky ReLU) on ``log(1 + sample)``, then a 1x1 head to ``K x K`` kernel logits at every sample;
  the parameter counts are therefore identical;
* gather: the kernel predicted at location ``p`` weighs the samples around ``p``
  (:func:`mcdenoise.ops.gather.gather`); splat: the kernel predicted at sample ``q`` spreads ``q``
  over the locations around it (:func:`mcdenoise.ops.splat.splat`); both normalised per output
  location by the weight that fell inside the image;
* the output image is the filtered grid at the output pixels' centres; loss = MSE against the
  blurred clean texture there.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import torch
import torch.nn.functional as F
from torch import nn

from mcdenoise.io.atomic import atomic_file
from mcdenoise.models.blocks import LEAK
from mcdenoise.ops.kernels import per_destination_exp, per_pixel_exp
from mcdenoise.ops.gather import gather
from mcdenoise.ops.splat import normalize_splat, splat

__all__ = ["ToyConfig", "ToyKernelNet", "make_textures", "make_batch", "run_experiment"]


@dataclass
class ToyConfig:
    """Settings of the splat-vs-gather experiment."""

    steps: int = 400
    """Adam steps per network."""
    seed: int = 0
    """Seeds textures, outliers and weight initialisation (both networks get the same data)."""
    batch: int = 8
    """Textures per training step."""
    size: int = 32
    """Side of the high-resolution sample grid of a training crop."""
    factor: int = 4
    """Downsampling factor: output pixels are ``factor x factor`` samples."""
    sigma: float = 1.5
    """Std. dev. (in samples) of the Gaussian that defines the anti-aliased target."""
    kernel_size: int = 9
    """Side of the predicted kernels, in samples (covers +-2.7 sigma)."""
    width: int = 32
    """Channels of the 3 conv layers (Fig. 4: 32)."""
    outlier_prob: float = 0.03
    """Probability that a sample is an outlier."""
    outlier_min: float = 10.0
    outlier_max: float = 50.0
    """An outlier adds a value drawn uniformly from [outlier_min, outlier_max] to the sample."""
    lr: float = 1e-3
    """Adam learning rate."""
    test_textures: int = 32
    """Held-out textures (other seed) the final losses are also measured on."""


class ToyKernelNet(nn.Module):
    """3 conv layers x ``width`` + 1x1 kernel head; ``mode`` "gather" or "splat".

    ``forward(samples (B, 3, H, W))`` -> filtered grid ``(B, 3, H, W)``.
    """

    def __init__(self, mode: str, kernel_size: int = 9, width: int = 32) -> None:
        super().__init__()
        if mode not in ("gather", "splat"):
            raise ValueError(f"mode must be 'gather' or 'splat', got {mode!r}")
        self.mode = mode
        self.kernel_size = kernel_size
        self.trunk = nn.Sequential(
            nn.Conv2d(3, width, 3, padding=1),
            nn.LeakyReLU(LEAK),
            nn.Conv2d(width, width, 3, padding=1),
            nn.LeakyReLU(LEAK),
            nn.Conv2d(width, width, 3, padding=1),
            nn.LeakyReLU(LEAK),
        )
        self.head = nn.Conv2d(width, kernel_size * kernel_size, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        logits = self.head(self.trunk(torch.log1p(x)))  # (B, K*K, H, W)
        b, _, h, w = x.shape
        k = self.kernel_size
        ones = torch.ones_like(x[:, :1])
        if self.mode == "gather":
            wts = per_pixel_exp(logits.unsqueeze(1))[:, 0]
            out = gather(torch.cat([x, ones], dim=1), wts)
            num, wsum = out[:, :3], out[:, 3:]
        else:
            wts = per_destination_exp(logits.unsqueeze(1), k)
            num, wsum = splat(x.unsqueeze(1), wts)
        return normalize_splat(num, wsum, 1e-8)


def count_parameters(m: nn.Module) -> int:
    return sum(p.numel() for p in m.parameters())


def _value_noise(b: int, size: int, cells: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    out = torch.empty(b, 3, size, size)
    for i in range(b):
        c = int(cells[i])
        grid = torch.rand(1, 3, c, c, generator=g)
        out[i] = F.interpolate(grid, size=(size, size), mode="bicubic", align_corners=False)[0]
    return out.clamp(0, 1)


def make_textures(n: int, size: int, g: torch.Generator) -> torch.Tensor:
    """``n`` procedural RGB textures ``(n, 3, size, size)`` in [0, 1], with detail near Nyquist."""
    yy, xx = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32), indexing="ij")
    out = torch.empty(n, 3, size, size)
    kinds = torch.randint(0, 4, (n,), generator=g)
    for i in range(n):
        c0, c1 = torch.rand(3, 1, 1, generator=g), torch.rand(3, 1, 1, generator=g)
        theta = float(torch.rand(1, generator=g)) * math.pi
        period = 3.0 + float(torch.rand(1, generator=g)) * 13.0
        u = xx * math.cos(theta) + yy * math.sin(theta)
        v = -xx * math.sin(theta) + yy * math.cos(theta)
        k = int(kinds[i])
        if k == 0:  # grating
            m = 0.5 + 0.5 * torch.sin(2 * math.pi * u / period)
        elif k == 1:  # rotated checkerboard
            m = ((torch.floor(u / period) + torch.floor(v / period)) % 2).float()
        elif k == 2:  # random discs
            m = torch.zeros(size, size)
            for _ in range(int(torch.randint(3, 12, (1,), generator=g))):
                cx, cy = torch.rand(2, generator=g) * size
                r = 2.0 + float(torch.rand(1, generator=g)) * size / 5
                m = torch.maximum(m, (((xx - cx) ** 2 + (yy - cy) ** 2) < r * r).float())
        else:  # value noise
            out[i] = _value_noise(1, size, torch.randint(4, 24, (1,), generator=g), g)[0]
            continue
        out[i] = c0 * m + c1 * (1 - m)
    return out


def _gaussian_target(clean: torch.Tensor, sigma: float, kernel_size: int) -> torch.Tensor:
    """Normalised Gaussian blur (in-image weights only, like the networks' normalisation)."""
    r = kernel_size // 2
    t = torch.arange(-r, r + 1, dtype=clean.dtype)
    g1 = torch.exp(-0.5 * (t / sigma) ** 2)
    k2 = (g1[:, None] * g1[None, :]).reshape(1, -1, 1, 1)
    b, _, h, w = clean.shape
    wts = k2.expand(b, -1, h, w).contiguous()
    out = gather(torch.cat([clean, torch.ones_like(clean[:, :1])], dim=1), wts)
    return out[:, :3] / out[:, 3:]


def make_batch(cfg: ToyConfig, n: int, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """``(noisy samples (n, 3, S, S), clean blurred target (n, 3, S, S))``, S = ``cfg.size``."""
    clean = make_textures(n, cfg.size, g)
    target = _gaussian_target(clean, cfg.sigma, cfg.kernel_size)
    hit = torch.rand(n, 1, cfg.size, cfg.size, generator=g) < cfg.outlier_prob
    energy = cfg.outlier_min + (cfg.outlier_max - cfg.outlier_min) * torch.rand(n, 1, cfg.size, cfg.size, generator=g)
    noisy = clean + hit * energy
    return noisy, target


def downsample(x: torch.Tensor, factor: int) -> torch.Tensor:
    """Values at the output pixels' centres: ``(B, C, H, W)`` -> ``(B, C, H/f, W/f)``."""
    o = factor // 2
    return x[..., o::factor, o::factor]


def _loss(net: nn.Module, noisy: torch.Tensor, target: torch.Tensor, factor: int) -> torch.Tensor:
    return F.mse_loss(downsample(net(noisy), factor), downsample(target, factor))


def run_experiment(cfg: ToyConfig, log: Callable[[str], None] = print) -> dict:
    """Train the gather and splat networks on identical data; return losses and curves."""
    torch.manual_seed(cfg.seed)
    nets = {m: ToyKernelNet(m, cfg.kernel_size, cfg.width) for m in ("gather", "splat")}
    # Same initial trunk and head: the networks differ only in how the kernel is applied.
    nets["splat"].load_state_dict(nets["gather"].state_dict())
    params = {m: count_parameters(n) for m, n in nets.items()}
    opts = {m: torch.optim.Adam(n.parameters(), lr=cfg.lr) for m, n in nets.items()}
    curves: dict[str, list[float]] = {m: [] for m in nets}
    g = torch.Generator().manual_seed(cfg.seed)
    t0 = time.perf_counter()
    for step in range(cfg.steps):
        noisy, target = make_batch(cfg, cfg.batch, g)
        for m, net in nets.items():
            opts[m].zero_grad()
            loss = _loss(net, noisy, target, cfg.factor)
            loss.backward()
            opts[m].step()
            curves[m].append(loss.item())
        if (step + 1) % max(1, cfg.steps // 10) == 0 or step + 1 == cfg.steps:
            log(f"step {step + 1}/{cfg.steps}: gather {curves['gather'][-1]:.5f}  splat {curves['splat'][-1]:.5f}")
    train_time = time.perf_counter() - t0
    tail = max(1, cfg.steps // 10)
    final_train = {m: sum(c[-tail:]) / len(c[-tail:]) for m, c in curves.items()}
    gt = torch.Generator().manual_seed(cfg.seed + 1_000_003)
    noisy, target = make_batch(cfg, cfg.test_textures, gt)
    with torch.no_grad():
        test = {m: float(_loss(net.eval(), noisy, target, cfg.factor)) for m, net in nets.items()}
        # Reference points: the plain Gaussian (what both nets would learn without outliers).
        gauss = float(F.mse_loss(downsample(_gaussian_target(noisy, cfg.sigma, cfg.kernel_size), cfg.factor),
                                 downsample(target, cfg.factor)))
    return {
        "experiment": "splat-vs-gather",
        "config": asdict(cfg),
        "parameters": params,
        "final_train_loss": final_train,
        "test_loss": test,
        "test_loss_fixed_gaussian": gauss,
        "train_seconds": train_time,
        "curves": curves,
    }


def write_result(result: dict, out_dir: str | Path) -> Path:
    """Write ``result`` as ``<out_dir>/splat_vs_gather.json`` atomically; returns the path."""
    path = Path(out_dir) / "splat_vs_gather.json"
    with atomic_file(path) as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    return path
