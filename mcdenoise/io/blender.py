"""Blender Cycles' conventions, in one place (issue 21): what its multi-layer EXR holds, how that
differs from our own format, and the Blender-ready output file.

The channel *names* are mapped in :mod:`mcdenoise.io.names` (``<ViewLayer>.Noisy Image.R`` ->
``radiance``, ``Denoising Albedo`` -> ``albedo``, ``Denoising Normal`` -> ``normal``,
``Denoising Depth`` -> ``depth``). The *contents* differ from ours in three ways:

* **Colour.** ``Noisy Image`` is written only while Blender's own denoiser is on (its result is
  then in ``Combined``). With the denoiser off there is no ``Noisy Image`` and the noisy colour is
  ``Combined``: :func:`colour_fallback` takes it, with a one-line note.
* **Normals are in camera space** (x right, y up, z along the view direction: a surface facing
  the camera reads z = -1), not world space as our renderer writes them; they follow mirror and
  glass bounces to the next rough surface. A light seen directly has its own normal (an area
  light's facing normal, a point light's normal toward the camera); the sky has 0. Decision: when the file's header carries the
  OpenEXR standard attribute ``worldToCamera`` (a 4x4 matrix, row-vector convention, camera
  space as above) the normals are rotated to world space (:func:`normals_to_world`); otherwise they
  are fed **as they are**. Blender 4.5 writes no camera matrix, so in practice they go in as camera
  space, and that is defensible: OIDN, the default method, takes normals "in world or view space"
  alike; our models read normals through local differences and a fixed [0, 1] map, and the shipped
  ones were trained on world-space normals, so on Blender files they see a rotated but otherwise
  alike distribution. Guessing a camera (none is written) would be worse than either.
* **Albedo exceeds 1 on lights and sky.** Cycles writes the emission colour where a light is seen
  directly or in a mirror (up to 1651 in issue 21's scenes) and the background colour on sky
  pixels (up to 20 there, up to 4000 on a Nishita sky), normal 0 on the sky; ours writes [0, 1] and
  0 on a miss. ``Denoising Depth`` is the distance along the camera ray and 0 on the sky, as ours.
  (All checked on Blender 4.5 renders: ``tests/test_blender_cycles.py``.) The values are passed
  on unchanged (OIDN is given what Blender gives its own OIDN); every model treats a pixel with an
  albedo above 1 as an emitter, passed through unfiltered (:mod:`mcdenoise.models.emitters`).

* **Diffuse and specular.** With the Diffuse Direct, Indirect and Color passes on, the colour is
  split as KPCN needs it (:func:`light_split`). Cycles files them by the first bounce's BSDF, so
  a diffuse wall seen through glass is Blender's transmission (our ``specular``), where our
  renderer, which looks through delta lobes, calls it diffuse.

A file with several view layers is read from one (:func:`view_layer`), colour and guides alike.

Output (:func:`blender_output`): every input channel is written back bit for bit (same pixel type),
with every header attribute, and the result is added as its own pass ``<ViewLayer>.Denoised``
(R, G, B and the colour pass's alpha), or written into ``Combined`` with ``replace_combined``, so
the file drops into a compositor setup that reads passes from it.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.errors import McDenoiseError

__all__ = [
    "CYCLES_PASSES", "DENOISED_PASS", "DIFFUSE_PASSES", "BlenderNote", "is_cycles", "view_layers", "view_layer",
    "colour_layer", "colour_fallback", "light_split", "normals_to_world", "apply_conventions", "blender_output",
]

#: Pass names of a Cycles multi-layer EXR with denoising data (Blender 4.x).
CYCLES_PASSES = ("Combined", "Noisy Image", "Denoising Albedo", "Denoising Normal", "Denoising Depth")
#: The pass the result is written to.
DENOISED_PASS = "Denoised"
#: Header attributes that describe the channel list and pixel layout (written by the library).
_STRUCTURAL = ("channels",)


class BlenderNote(UserWarning):
    """A one-line note on how a Blender file was read (printed by ``mcdenoise denoise``)."""


def _pass_of(channel: str) -> tuple[str, str, str]:
    """``"ViewLayer.Noisy Image.R"`` -> ``("ViewLayer.", "Noisy Image", "R")``; ``"R"`` -> ``("", "", "R")``."""
    layer, _, comp = channel.rpartition(".")
    prefix, _, name = layer.rpartition(".")
    return (prefix + "." if prefix else ""), name, comp


def _prefix_of(layer: str) -> str:
    """The view-layer prefix of a layer name's part before its pass: ``"ViewLayer"`` ->
    ``"ViewLayer."``, ``""`` (a pass without one, as Blender 5's File Output writes) -> ``""``."""
    return f"{layer}." if layer else ""


def is_cycles(channel_names: list[str]) -> bool:
    """Does the channel list look like a Cycles multi-layer EXR (a Cycles colour or denoising
    pass, under a view-layer prefix as Blender 4 writes a render, or without one as Blender 5's
    File Output node writes its inputs)?"""
    return any(name in CYCLES_PASSES for _, name, _ in map(_pass_of, channel_names))


def view_layers(channel_names: list[str]) -> list[str]:
    """The view-layer prefixes (``"ViewLayer."``; ``""`` for passes without one) that hold a Cycles
    pass, in name order."""
    return sorted({prefix for prefix, name, _ in map(_pass_of, channel_names) if name in CYCLES_PASSES})


#: What a view layer needs to be read, most important first (a layer is scored by how many it has).
_WANTED = ("Noisy Image", "Denoising Albedo", "Denoising Normal", "Denoising Depth")


def view_layer(channel_names: list[str]) -> str | None:
    """The view layer (its prefix) whose passes are read, and beside which the result is written.

    A file with several view layers (one per ``View Layer`` in Blender, each with its own passes)
    is read from **one**: the layer with a colour pass (``Noisy Image`` or ``Combined``) that has
    the most of ``Noisy Image`` and the three denoising passes, the first by name among equals
    (OpenEXR sorts channels by name, so Blender's own layer order is not in the file). Reading the
    colour of one layer and the guides of another (the first of each by name, as before) mixed
    layers that may show different objects. None when no layer has a colour pass."""
    passes: dict[str, set[str]] = {}
    for prefix, name, _ in map(_pass_of, channel_names):
        if name:
            passes.setdefault(prefix, set()).add(name)
    candidates = [p for p in sorted(passes) if passes[p] & {"Noisy Image", "Combined"}]
    if not candidates:
        return None
    return max(candidates, key=lambda p: (len(passes[p] & set(_WANTED)), -candidates.index(p)))


def colour_layer(channel_names: list[str]) -> tuple[str, str] | None:
    """``(view-layer prefix, pass)`` of the colour the denoiser reads, in :func:`view_layer`'s layer:
    ``Noisy Image`` if it has one, else ``Combined``; None when no layer has either."""
    prefix = view_layer(channel_names)
    if prefix is None:
        return None
    names = {name for p, name, _ in map(_pass_of, channel_names) if p == prefix}
    return prefix, "Noisy Image" if "Noisy Image" in names else "Combined"


def colour_fallback(layers: dict[str, np.ndarray], path: Path, prefix: str | None = None) -> np.ndarray | None:
    """``Combined``'s RGB (3, H, W) when the file has no ``Noisy Image`` (Blender's denoiser off),
    with a :class:`BlenderNote`; None when there is no ``Combined`` either. ``prefix``: the view
    layer to take it from (:func:`view_layer`); None takes the first."""
    for name, arr in layers.items():
        layer, _, pass_name = name.rpartition(".")
        if pass_name == "Combined" and arr.shape[0] >= 3 and (prefix is None or _prefix_of(layer) == prefix):
            warnings.warn(f"{path}: no 'Noisy Image' pass (Blender's denoiser was off): denoising '{name}'",
                          BlenderNote, stacklevel=2)
            return arr[:3]
    return None


def normals_to_world(normal: np.ndarray, world_to_camera: Any) -> np.ndarray:
    """Camera-space normals (3, H, W) -> world space, with the header's ``worldToCamera`` (4x4,
    row vectors: ``p_cam = p_world @ M``). Normals map with the inverse transpose of the linear
    part, so ``n_world = n_cam @ M3.T`` up to length; unit length is restored, zeros stay 0."""
    m = np.asarray(world_to_camera, dtype=np.float64).reshape(4, 4)[:3, :3]
    n = np.einsum("chw,dc->dhw", normal.astype(np.float64), m)  # (n_cam @ M3.T) per pixel
    length = np.sqrt((n * n).sum(axis=0, keepdims=True))
    scale = np.where(length > 0, np.sqrt((normal.astype(np.float64) ** 2).sum(axis=0, keepdims=True))
                     / np.where(length > 0, length, 1), 0)
    return (n * scale).astype(np.float32)


#: Cycles' light passes (EXR layer names) of the diffuse lobe: ``(DiffDir + DiffInd) * DiffCol``
#: is the diffuse part of ``Combined``; the rest (glossy, transmission, emission, environment,
#: volume) is the specular part, as KPCN splits it.
DIFFUSE_PASSES = ("DiffDir", "DiffInd", "DiffCol")


def light_split(layers: dict[str, np.ndarray], radiance: np.ndarray, prefix: str | None = None
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """``(diffuse, specular)``, each (3, H, W) and >= 0 with ``diffuse + specular == radiance``,
    from Cycles' Diffuse Direct, Indirect and Color passes (``prefix``: the view layer, None = any);
    None when one of them is missing. Cycles stores the light passes divided by the colour pass
    (checked: the sum of every lobe's ``(Dir + Ind) * Col`` plus Emit and Env equals ``Combined``
    to 1e-7 relative on a glass scene), so ``(DiffDir + DiffInd) * DiffCol`` is the diffuse
    radiance, and the remainder of the colour is specular. Where Blender's denoiser ran, the
    colour is ``Noisy Image``, from the same samples."""
    found: dict[str, np.ndarray] = {}
    for name, arr in layers.items():
        layer, _, pass_name = name.rpartition(".")
        if pass_name in DIFFUSE_PASSES and arr.shape[0] >= 3 and (prefix is None or _prefix_of(layer) == prefix):
            found.setdefault(pass_name, arr[:3].astype(np.float32))
    if len(found) < len(DIFFUSE_PASSES):
        return None
    diffuse = (found["DiffDir"] + found["DiffInd"]) * found["DiffCol"]
    rad = radiance.astype(np.float32)
    # Within [0, radiance]: rounding (and half-float passes) must not make specular negative.
    diffuse = np.clip(diffuse, 0.0, np.maximum(rad, 0.0))
    return diffuse, rad - diffuse


def apply_conventions(layers: dict[str, np.ndarray], header: dict[str, Any], path: Path) -> dict[str, np.ndarray]:
    """Our reading of a Cycles file's layers (from :func:`mcdenoise.io.exr.read_exr`), see the
    module docstring: the ``Combined`` fallback and world-space normals when the header allows;
    a note naming the view layer read when the file has several (:func:`view_layer`)."""
    names = [c.name for c in header.get("channels", ())]
    prefix = view_layer(names) if names else None
    others = [p for p in view_layers(names) if p != prefix]
    if prefix is not None and others:
        warnings.warn(f"{path}: {len(others) + 1} view layers; reading '{prefix[:-1]}' (the one with the most "
                      f"denoising passes), not {', '.join(repr(p[:-1]) for p in others)}", BlenderNote, stacklevel=2)
    if "radiance" not in layers:
        rgb = colour_fallback(layers, path, prefix)
        if rgb is not None:
            layers["radiance"] = rgb
    if "radiance" in layers and "diffuse" not in layers:
        split = light_split(layers, layers["radiance"], prefix)
        if split is not None:
            layers["diffuse"], layers["specular"] = split
    w2c = header.get("worldToCamera")
    if "normal" in layers and w2c is not None:
        layers["normal"] = normals_to_world(layers["normal"], w2c)
    return layers


def blender_output(
    channels: dict[str, np.ndarray], header: dict[str, Any], result: np.ndarray, *,
    replace_combined: bool = False, path: Path | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The Blender-ready output: every input channel (native dtype, untouched), every header
    attribute, and ``result`` (3, H, W) as ``<ViewLayer>.Denoised.R/G/B`` (plus the colour pass's
    alpha as ``.A``), or in ``Combined`` with ``replace_combined`` (its alpha kept; a half
    ``Combined`` stays half). Returns the channels and the header to write."""
    names = list(channels)
    where = colour_layer(names)
    if where is None:
        raise McDenoiseError(f"{path}: no 'Noisy Image' or 'Combined' pass to place the result beside")
    prefix, colour = where
    out = dict(channels)
    alpha = channels.get(f"{prefix}{colour}.A")
    target = "Combined" if replace_combined else DENOISED_PASS
    for i, c in enumerate("RGB"):
        key = f"{prefix}{target}.{c}"
        dtype = channels[key].dtype if key in channels and channels[key].dtype == np.float16 else np.float32
        out[key] = np.ascontiguousarray(result[i], dtype=dtype)
    if alpha is not None and f"{prefix}{target}.A" not in out:
        out[f"{prefix}{target}.A"] = alpha
    head = {k: v for k, v in header.items() if k not in _STRUCTURAL}
    return out, head
