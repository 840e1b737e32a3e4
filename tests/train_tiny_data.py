"""A tiny synthetic dataset (numpy only, no renderer) with every per-sample channel any model reads.

Each image has a smooth reference (a few sinusoids scaled by a per-image albedo) and samples that
are the reference times heavy-tailed positive noise, so every model can learn something in a
few steps. Used by the training tests; writes in well under a second.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mcdenoise.data.channels import LOBE_TYPES, LOBE_VERTICES
from mcdenoise.data.dataset import write_manifest
from mcdenoise.data.format import ImageMeta, write_image

#: Every per-sample channel some registered model asks for.
SAMPLE_CHANNELS = ("radiance", "diffuse", "specular", "albedo", "normal", "depth", "albedo_diffuse", "normal_diffuse",
                   "depth_diffuse", "roughness", "visibility", "lobes", "subpixel", "lens", "time")


def _image(rng: np.random.Generator, spp: int, size: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    h = w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / size
    f = rng.uniform(1.0, 4.0, size=2)
    albedo = np.stack([0.2 + 0.6 * rng.random() * (0.5 + 0.5 * np.sin(2 * np.pi * (f[0] * xx + c))) for c in (0.0, 0.3, 0.6)])
    light = 0.5 + 1.5 * (0.5 + 0.5 * np.cos(2 * np.pi * f[1] * yy))[None].repeat(3, 0)
    ref_diffuse = (albedo * light).astype(np.float32)
    ref_specular = (0.2 * light * (xx > 0.5)).astype(np.float32)
    noise = rng.gamma(0.7, 1 / 0.7, size=(spp, 1, h, w)).astype(np.float32)
    noise_s = rng.gamma(0.5, 1 / 0.5, size=(spp, 1, h, w)).astype(np.float32)
    diffuse = ref_diffuse[None] * noise
    specular = ref_specular[None] * noise_s
    normal = np.zeros((spp, 3, h, w), np.float32)
    normal[:, 2] = 1.0
    depth = np.broadcast_to(1.0 + yy, (spp, 1, h, w)).astype(np.float32)
    lobes = np.zeros((spp, len(LOBE_TYPES) * LOBE_VERTICES, h, w), np.float32)
    lobes[:, 2] = 1.0
    smp = {
        "radiance": diffuse + specular,
        "diffuse": diffuse,
        "specular": specular,
        "albedo": np.broadcast_to(albedo, (spp, 3, h, w)),
        "normal": normal,
        "depth": depth,
        "albedo_diffuse": np.broadcast_to(albedo, (spp, 3, h, w)),
        "normal_diffuse": normal,
        "depth_diffuse": depth,
        "roughness": np.ones((spp, 1, h, w), np.float32),
        "visibility": (rng.random((spp, 1, h, w)) < 0.8).astype(np.float32),
        "lobes": lobes,
        "subpixel": rng.random((spp, 2, h, w)),
        "lens": np.zeros((spp, 2, h, w), np.float32),
        "time": rng.random((spp, 1, h, w)),
    }
    # Half-stored channels must hold float16-representable values to round-trip exactly.
    smp = {k: np.ascontiguousarray(v, dtype=np.float32).astype(np.float16).astype(np.float32) if k not in ("radiance", "diffuse", "specular", "depth", "depth_diffuse") else np.ascontiguousarray(v, dtype=np.float32) for k, v in smp.items()}
    ref = {"radiance": ref_diffuse + ref_specular, "diffuse": ref_diffuse, "specular": ref_specular,
           "albedo": albedo.astype(np.float32)}
    return smp, ref


def make_tiny_dataset(root: Path, *, train: int = 3, val: int = 1, spp: int = 8, size: int = 24, seed: int = 0) -> Path:
    """Write ``train`` + ``val`` images of ``size x size`` at ``spp`` into ``root`` with a manifest."""
    rng = np.random.default_rng(seed)
    entries = []
    for i in range(train + val):
        split = "train" if i < train else "val"
        smp, ref = _image(rng, spp, size)
        meta = ImageMeta(width=size, height=size, spp=spp, channels=list(SAMPLE_CHANNELS), scene=f"s{i}", seed=i,
                         renderer="tests/train_tiny_data", scene_features={"fov": 40.0}, reference_spp=1024)
        rel = f"{split}/{i:03d}"
        write_image(root / rel, meta=meta, samples=smp, reference=ref, tile=8)
        entries.append({"path": rel, "scene": f"s{i}", "split": split})
    write_manifest(root, entries)
    return root
