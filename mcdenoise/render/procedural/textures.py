"""Procedural textures and HDR environment maps, made as numpy arrays from a seeded generator.

Texture images are tileable (UVs are scaled by random factors, so the pattern repeats) and hold
reflectances in [0, 1]; environment maps are linear HDR latitude-longitude images in Mitsuba's
convention (rows from +Y down to -Y, columns around the Y axis).
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "tileable_noise",
    "stripes",
    "cells",
    "colorize",
    "texture_image",
    "TEXTURE_KINDS",
    "sky_envmap",
    "studio_envmap",
    "envmap_image",
]


def tileable_noise(rng: np.random.Generator, size: int, beta: float = 2.0) -> np.ndarray:
    """Periodic fractal noise (size, size) in [0, 1] from a 1/f^beta spectrum (periodic by FFT)."""
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = 1.0
    amp = f ** (-beta / 2)
    amp[0, 0] = 0.0
    spec = amp * (rng.normal(size=amp.shape) + 1j * rng.normal(size=amp.shape))
    img = np.fft.irfft2(spec, s=(size, size))
    lo, hi = img.min(), img.max()
    return (img - lo) / max(hi - lo, 1e-12)


def stripes(rng: np.random.Generator, size: int) -> np.ndarray:
    """Periodic stripes (size, size) in [0, 1]: integer wave vectors keep them tileable."""
    kx, ky = rng.integers(0, 9, size=2)
    if kx == 0 and ky == 0:
        kx = 1
    y, x = np.mgrid[0:size, 0:size] / size
    wave = np.sin(2 * np.pi * (kx * x + ky * y))
    sharp = rng.uniform(1.0, 20.0)  # from soft bands to hard-edged stripes
    return 0.5 + 0.5 * np.tanh(sharp * wave) / np.tanh(sharp)


def cells(rng: np.random.Generator, size: int) -> np.ndarray:
    """Periodic Worley cells (size, size) in [0, 1]: distance to the nearest of random points."""
    n = int(rng.integers(4, 24))
    pts = rng.random((n, 2))
    y, x = np.mgrid[0:size, 0:size] / size
    d = np.full((size, size), np.inf)
    for px, py in pts:
        dx = np.abs(x - px)
        dy = np.abs(y - py)
        dx = np.minimum(dx, 1 - dx)  # wrap-around distance: periodic
        dy = np.minimum(dy, 1 - dy)
        d = np.minimum(d, np.sqrt(dx * dx + dy * dy))
    return d / max(d.max(), 1e-12)


def colorize(rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """Map a scalar image ``t`` (H, W) in [0, 1] through a random 2-4 colour ramp -> (H, W, 3)."""
    k = int(rng.integers(2, 5))
    stops = np.sort(np.concatenate([[0.0, 1.0], rng.random(k - 2)]))
    colors = rng.uniform(0.02, 0.95, size=(k, 3))
    out = np.stack([np.interp(t, stops, colors[:, c]) for c in range(3)], -1)
    return out.astype(np.float32)


TEXTURE_KINDS = ("noise", "stripes", "cells", "noise_stripes")


def texture_image(rng: np.random.Generator, kind: str, size: int = 128) -> np.ndarray:
    """An RGB reflectance texture (size, size, 3) float32 in [0.02, 0.95] of the given kind."""
    if kind == "noise":
        t = tileable_noise(rng, size, beta=rng.uniform(1.0, 3.5))
    elif kind == "stripes":
        t = stripes(rng, size)
    elif kind == "cells":
        t = cells(rng, size)
    elif kind == "noise_stripes":
        # Wood-like: stripes warped by noise.
        t = np.mod(stripes(rng, size) * 2 + tileable_noise(rng, size, 2.5) * rng.uniform(1, 4), 1.0)
    else:
        raise ValueError(f"unknown texture kind {kind!r}; kinds: {TEXTURE_KINDS}")
    return colorize(rng, t)


def _directions(h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit directions (h, w, 3) at the pixel centres of a lat-long map, and their theta, phi."""
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)
    return d, th, ph


def sky_envmap(rng: np.random.Generator, height: int = 128, width: int = 256) -> np.ndarray:
    """A daylight-like sky: zenith-to-horizon gradient, noise clouds, a dim ground and a small,
    very bright sun disc (sun/sky ratio of a few hundred to thousands, as in real HDR probes)."""
    d, th, ph = _directions(height, width)
    up = d[..., 1]
    zenith = rng.uniform([0.05, 0.15, 0.4], [0.3, 0.45, 1.0])
    horizon = rng.uniform([0.5, 0.5, 0.5], [1.0, 1.0, 1.0])
    ground = rng.uniform(0.05, 0.3, 3) * rng.uniform(0.2, 1.0)
    t = np.clip(up, 0, 1)[..., None] ** rng.uniform(0.3, 0.8)
    sky = horizon * (1 - t) + zenith * t
    cloud = tileable_noise(rng, max(height, width), beta=rng.uniform(2.0, 3.0))
    cloud = cloud[:height, :width]
    cover = rng.uniform(0.0, 0.9)
    cloud = np.clip((cloud - (1 - cover)) / max(cover, 1e-3), 0, 1)[..., None] * (up > 0)[..., None]
    sky = sky * (1 - cloud) + cloud * rng.uniform(0.6, 1.2)
    img = np.where((up > 0)[..., None], sky, ground)
    # Sun: a disc of angular radius r and radiance scaled so that its power is a random factor
    # of the sky's.
    elev = rng.uniform(0.05, 1.4)
    azim = rng.uniform(0, 2 * np.pi)
    sd = np.array([np.cos(elev) * np.sin(azim), np.sin(elev), -np.cos(elev) * np.cos(azim)])
    radius = rng.uniform(0.02, 0.06)
    cosang = np.clip(d @ sd, -1, 1)
    disc = np.arccos(cosang) < radius
    if not disc.any():  # at coarse resolutions keep at least the nearest pixel
        disc = cosang == cosang.max()
    sun_color = np.array([1.0, rng.uniform(0.8, 1.0), rng.uniform(0.6, 0.95)])
    img[disc] = sun_color * rng.uniform(200.0, 3000.0) * (1 - 0.7 * cover)
    img *= rng.uniform(0.5, 2.0)
    return img.astype(np.float32)


def studio_envmap(rng: np.random.Generator, height: int = 128, width: int = 256) -> np.ndarray:
    """A dark studio with 1-4 bright rectangular soft boxes."""
    d, th, ph = _directions(height, width)
    img = np.zeros((height, width, 3)) + rng.uniform(0.005, 0.05, 3)
    for _ in range(int(rng.integers(1, 5))):
        c_th = rng.uniform(0.2, 1.6)
        c_ph = rng.uniform(0, 2 * np.pi)
        h_th = rng.uniform(0.05, 0.3)
        h_ph = rng.uniform(0.05, 0.5)
        dph = np.angle(np.exp(1j * (ph - c_ph)))
        box = (np.abs(th - c_th) < h_th) & (np.abs(dph) < h_ph)
        img[box] += rng.uniform(0.5, 1.0, 3) * rng.uniform(5.0, 60.0)
    return img.astype(np.float32)


def envmap_image(rng: np.random.Generator, height: int = 128, width: int = 256) -> tuple[str, np.ndarray]:
    """A random environment map: ``("sky" | "studio", image (height, width, 3))``."""
    if rng.random() < 0.75:
        return "sky", sky_envmap(rng, height, width)
    return "studio", studio_envmap(rng, height, width)
