"""Random textures and BSDFs (Mitsuba plugin dicts) of the scene generator.

:data:`MATERIALS` and :data:`TEXTURES` are the kinds drawn and their weights; texture images come
from :mod:`mcdenoise.render.procedural.textures`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mcdenoise.render._mitsuba import mitsuba
from mcdenoise.render.procedural import textures as pt
from mcdenoise.render.procedural.seeds import _choice, _loguniform
from mcdenoise.render.procedural.transforms import _rotate, _scale, _xform

__all__ = ["MATERIALS", "TEXTURES", "CONDUCTORS"]


#: material plugin -> weight. Diffuse is favoured slightly, as in SBMC.
MATERIALS: dict[str, float] = {
    "diffuse": 0.2,
    "plastic": 0.1,
    "roughplastic": 0.15,
    "conductor": 0.07,
    "roughconductor": 0.13,
    "dielectric": 0.07,
    "roughdielectric": 0.08,
    "principled": 0.2,
}
#: texture kind -> weight, for colour parameters.
TEXTURES: dict[str, float] = {
    "constant": 0.35,
    "checkerboard": 0.15,
    "noise": 0.15,
    "stripes": 0.1,
    "cells": 0.1,
    "noise_stripes": 0.15,
}
CONDUCTORS = ("Au", "Ag", "Al", "Cu", "Cr", "W", "Hg", "Ir", "Rh", "none")  # all ship with Mitsuba 3.9


def _bitmap(arr: np.ndarray) -> Any:
    return mitsuba().Bitmap(np.ascontiguousarray(arr, np.float32))



def _texture(rng: np.random.Generator, used: dict[str, int], *, lo: float = 0.02, hi: float = 0.95) -> dict:
    """A colour texture plugin dict (constant, checkerboard or bitmap) with a random UV scale."""
    kind = _choice(rng, TEXTURES)
    used[kind] = used.get(kind, 0) + 1
    if kind == "constant":
        return {"type": "rgb", "value": rng.uniform(lo, hi, 3).tolist()}
    uv = _loguniform(rng, 0.5, 16.0)
    to_uv = _xform(_rotate([0, 0, 1], rng.uniform(0, 2 * np.pi)) @ _scale([uv, uv * rng.uniform(0.5, 2.0), 1.0]))
    if kind == "checkerboard":
        return {
            "type": "checkerboard",
            "color0": {"type": "rgb", "value": rng.uniform(lo, hi, 3).tolist()},
            "color1": {"type": "rgb", "value": rng.uniform(lo, hi, 3).tolist()},
            "to_uv": to_uv,
        }
    size = int(rng.choice([32, 64, 128]))
    img = lo + (hi - lo) * pt.texture_image(rng, kind, size)
    return {"type": "bitmap", "bitmap": _bitmap(img), "to_uv": to_uv, "raw": True, "filter_type": "bilinear"}


def _material(rng: np.random.Generator, used: dict[str, int], textures: dict[str, int], kind: str | None = None) -> dict:
    """A random BSDF plugin dict; ``used`` counts material kinds, ``textures`` texture kinds."""
    kind = kind or _choice(rng, MATERIALS)
    used[kind] = used.get(kind, 0) + 1
    alpha = _loguniform(rng, 0.02, 0.6)
    ior = float(rng.uniform(1.3, 1.9))
    if kind == "diffuse":
        bsdf: dict = {"type": "diffuse", "reflectance": _texture(rng, textures)}
    elif kind == "plastic":
        bsdf = {"type": "plastic", "diffuse_reflectance": _texture(rng, textures), "int_ior": ior}
    elif kind == "roughplastic":
        bsdf = {"type": "roughplastic", "diffuse_reflectance": _texture(rng, textures), "int_ior": ior, "alpha": alpha}
    elif kind == "conductor":
        bsdf = {"type": "conductor", "material": str(rng.choice(CONDUCTORS))}
        if bsdf["material"] == "none" or rng.random() < 0.3:
            bsdf["specular_reflectance"] = _texture(rng, textures, lo=0.3, hi=1.0)
    elif kind == "roughconductor":
        bsdf = {
            "type": "roughconductor",
            "material": str(rng.choice(CONDUCTORS)),
            "distribution": str(rng.choice(["ggx", "beckmann"])),
            "alpha": alpha,
        }
        if bsdf["material"] == "none" or rng.random() < 0.3:
            bsdf["specular_reflectance"] = _texture(rng, textures, lo=0.3, hi=1.0)
    elif kind == "dielectric":
        bsdf = {"type": "dielectric", "int_ior": ior}
        if rng.random() < 0.3:
            bsdf["specular_transmittance"] = {"type": "rgb", "value": rng.uniform(0.5, 1.0, 3).tolist()}
    elif kind == "roughdielectric":
        bsdf = {"type": "roughdielectric", "int_ior": ior, "alpha": alpha, "distribution": "ggx"}
    elif kind == "principled":
        bsdf = {
            "type": "principled",
            "base_color": _texture(rng, textures),
            "roughness": float(rng.uniform(0.05, 1.0)),
            "metallic": float(rng.choice([0.0, 0.0, 1.0, rng.uniform()])),
            "specular": float(rng.uniform(0.0, 1.0)),
            "spec_trans": float(rng.choice([0.0, 0.0, 0.0, rng.uniform()])),
            "clearcoat": float(rng.choice([0.0, rng.uniform()])),
            "clearcoat_gloss": float(rng.uniform()),
            "sheen": float(rng.choice([0.0, rng.uniform()])),
            "anisotropic": float(rng.choice([0.0, 0.0, rng.uniform()])),
        }
    else:
        raise ValueError(f"unknown material {kind!r}; materials: {sorted(MATERIALS)}")
    # Bump maps on some opaque materials (Mitsuba's bumpmap needs a raw scalar texture).
    if kind not in ("dielectric", "roughdielectric") and rng.random() < 0.2:
        size = 64
        h = pt.tileable_noise(rng, size, beta=rng.uniform(1.5, 3.0)) if rng.random() < 0.6 else pt.stripes(rng, size)
        uv = _loguniform(rng, 1.0, 16.0)
        textures["bump"] = textures.get("bump", 0) + 1
        bsdf = {
            "type": "bumpmap",
            "arg": {"type": "bitmap", "bitmap": _bitmap(h[..., None]), "raw": True, "to_uv": _xform(_scale([uv, uv, 1]))},
            "scale": float(rng.uniform(0.05, 0.5)),
            "nested": bsdf,
        }
    return bsdf
