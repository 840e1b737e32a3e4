"""What to denoise: per-pixel buffers and, optionally, per-sample buffers, read a window at a time.

Three ways in, one :class:`Inputs` out:

* :func:`from_exr` -- one multi-layer EXR in any naming of :mod:`mcdenoise.io.names` (Blender
  Cycles, Mitsuba 3 aov, pbrt-v4 GBufferFilm, ours), optionally with separate single-image files
  for albedo, normal and depth (how OIDN's tools take them: ``color.exr --albedo alb.exr``);
* :func:`from_folder` -- an image folder of ``mcdenoise render``: ``noisy.exr`` for the pixel
  models and ``samples.bin`` (read a window at a time, never whole) for the sample models;
* :func:`from_arrays` -- numpy arrays (the Python API), channel-first ``(C, H, W)`` pixels and
  ``(S, C, H, W)`` samples.

Non-finite input values (NaN, Inf) are replaced by 0 and counted; :meth:`Inputs.warn_nonfinite`
reports the count once.
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

import numpy as np
import torch

from mcdenoise.data.channels import CHANNELS, SCENE_FEATURES, base_name, num_components
from mcdenoise.data.oidn_input import OIDN_CHANNELS
from mcdenoise.errors import FormatError, McDenoiseError

__all__ = ["NonFiniteInputWarning", "InputError", "Inputs", "from_exr", "from_folder", "from_arrays"]

Box = tuple[int, int, int, int]


class NonFiniteInputWarning(UserWarning):
    """Input pixels or samples held NaN or Inf; they were replaced by 0."""


class InputError(McDenoiseError):
    """The input cannot be denoised as given: missing channels, sizes that differ..."""


def _sanitize(arr: np.ndarray) -> tuple[np.ndarray, int]:
    """float32 copy-if-needed of ``arr`` with NaN/Inf set to 0, and how many there were."""
    arr = np.asarray(arr, dtype=np.float32)
    # One pass without a mask first (1 ms against 3.7 for the mask at 1080p, issue 18): any NaN or
    # Inf makes the sum non-finite; a sum that overflows on finite values only falls through to
    # the exact count below.
    if np.isfinite(arr.sum()):
        return arr, 0
    bad = ~np.isfinite(arr)
    n = int(bad.sum())
    if n:
        arr = np.where(bad, np.float32(0), arr)
    return arr, n


class SampleSource(Protocol):
    """Per-sample buffers read a window at a time."""

    channels: list[str]
    spp: int
    nonfinite: int

    def read(self, names: list[str], window: Box, core: Box) -> dict[str, np.ndarray]:
        """name -> ``(S, C, h, w)`` float32 of ``window``; non-finite values inside ``core`` counted."""
        ...


_COUNT = re.compile(r"(\d+) non-finite value")


class FolderSamples:
    """``samples.bin`` of an image folder (:class:`mcdenoise.data.format.SampleReader`)."""

    def __init__(self, reader: object) -> None:
        self.reader = reader
        self.channels = list(reader.channels)  # type: ignore[attr-defined]
        self.spp = int(reader.spp)  # type: ignore[attr-defined]
        self.nonfinite = 0

    def _read_sanitized(self, names: list[str], crop: Box) -> tuple[dict[str, np.ndarray], int]:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            arrays = self.reader.read(names, crop=crop, sanitize=True)  # type: ignore[attr-defined]
        count = sum(int(m.group(1)) for w in caught if (m := _COUNT.search(str(w.message))))
        return arrays, count

    def read(self, names: list[str], window: Box, core: Box) -> dict[str, np.ndarray]:
        try:
            return self.reader.read(names, crop=window)  # type: ignore[attr-defined]
        except McDenoiseError as e:  # FormatError, or the reader's NonFiniteError where it has one
            if "non-finite" not in str(e):
                raise
        arrays, _ = self._read_sanitized(names, window)
        # Count over the core only: cores partition the image, windows overlap.
        self.nonfinite += self._read_sanitized(names, core)[1]
        return arrays


class ArraySamples:
    """Per-sample numpy arrays held in memory (the Python API)."""

    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self.arrays: dict[str, np.ndarray] = {}
        self.nonfinite = 0
        spp = None
        for name, arr in arrays.items():
            a = np.asarray(arr)
            if a.ndim != 4:
                raise InputError(f"samples[{name!r}]: expected (S, C, H, W), got shape {a.shape}")
            if spp is not None and a.shape[0] != spp:
                raise InputError(f"samples[{name!r}] has {a.shape[0]} samples, other channels {spp}")
            spp = a.shape[0]
            self.arrays[name], n = _sanitize(a)
            self.nonfinite += n
        self.channels = list(self.arrays)
        self.spp = int(spp or 0)

    def read(self, names: list[str], window: Box, core: Box) -> dict[str, np.ndarray]:
        y0, x0, h, w = window
        return {n: np.ascontiguousarray(self.arrays[n][..., y0 : y0 + h, x0 : x0 + w]) for n in names}


@dataclass
class Inputs:
    """Everything known about one image to denoise.

    Attributes:
        height, width: image size.
        pixels: vocabulary name (or ``*_variance``) -> ``(C, H, W)`` float32, finite.
        samples: per-sample buffers, or None.
        scene_features: ``(len(SCENE_FEATURES),)`` float32 (zeros when unknown).
        paths: files the input was read from (the output must not be one of them).
        label: how messages name the input.
        nonfinite: non-finite pixel values replaced so far.
        source: the renderer whose conventions the input follows when known (``"blender"`` for a
            Cycles file), else ``""``; the automatic pick skips models whose card says they are
            not for it (``not_for``, :mod:`mcdenoise.infer.choose`).
    """

    height: int
    width: int
    pixels: dict[str, np.ndarray]
    samples: SampleSource | None = None
    scene_features: np.ndarray = field(default_factory=lambda: np.zeros(len(SCENE_FEATURES), np.float32))
    paths: tuple[Path, ...] = ()
    label: str = "input"
    nonfinite: int = 0
    source: str = ""
    #: Deferred reading of the pixel buffers (image folders: a sample model never needs
    #: noisy.exr, which holds every channel and its variance -- 2.4 GB at 4K for SBMC's).
    loader: Callable[[Inputs], None] | None = None
    pixel_names: set[str] = field(default_factory=set)

    def ensure_pixels(self) -> None:
        """Read the deferred pixel buffers now (once)."""
        if self.loader is not None:
            load, self.loader = self.loader, None
            load(self)

    def channels(self, kind: str) -> set[str]:
        """Channels available to models of ``input_kind`` ``kind`` (``"pixels"`` or ``"samples"``)."""
        if kind == "samples":
            return set(self.samples.channels) if self.samples is not None else set()
        have = set(self.pixel_names) if self.loader is not None else set(self.pixels)
        if "radiance" in have:
            have.update(OIDN_CHANNELS)  # derived on demand (mcdenoise.infer.run.add_oidn)
        return have

    def batch(self, names: list[str], kind: str, window: Box, core: Box,
              device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """The model's batch of one for ``window``: ``(1, C, h, w)`` pixels or ``(1, S, C, h, w)``
        samples plus ``scene_features (1, F)``."""
        names = [n for n in names if n != "scene_features"]
        if kind == "samples":
            assert self.samples is not None
            arrays = self.samples.read(names, window, core)
            out = {k: torch.from_numpy(np.ascontiguousarray(v))[None].to(device) for k, v in arrays.items()}
            out["scene_features"] = torch.from_numpy(self.scene_features)[None].to(device)
            return out
        self.ensure_pixels()
        y0, x0, h, w = window
        return {n: torch.from_numpy(np.ascontiguousarray(self.pixels[n][:, y0 : y0 + h, x0 : x0 + w]))[None].to(device)
                for n in names}

    def total_nonfinite(self) -> int:
        return self.nonfinite + (self.samples.nonfinite if self.samples is not None else 0)

    def warn_nonfinite(self) -> None:
        """One warning giving the count of NaN/Inf input values replaced by 0 (none: no warning)."""
        n = self.total_nonfinite()
        if n:
            warnings.warn(f"{self.label}: {n} non-finite input value(s) (NaN or Inf) replaced by 0",
                          NonFiniteInputWarning, stacklevel=2)


def _add_pixels(inputs: Inputs, name: str, arr: np.ndarray, origin: str) -> None:
    """Check ``arr`` (C, H, W) against the vocabulary and the image size, sanitise, store."""
    base = base_name(name)
    if base in CHANNELS and arr.shape[0] != num_components(name):
        raise InputError(f"{origin}: {name!r} has {arr.shape[0]} components, expected {num_components(name)}")
    if arr.shape[1:] != (inputs.height, inputs.width):
        raise InputError(f"size mismatch: {origin} is {arr.shape[2]}x{arr.shape[1]} (WxH), "
                         f"{inputs.label} is {inputs.width}x{inputs.height}")
    clean, n = _sanitize(arr)
    inputs.nonfinite += n
    inputs.pixels[name] = clean


def _image_layer(layers: dict[str, np.ndarray], path: Path, want: str, comps: int) -> np.ndarray:
    """The one image of a single-feature file: the layer named ``want``, else its only RGB image."""
    if want in layers:
        return layers[want]
    for name in ("radiance", "image"):
        if name in layers and layers[name].shape[0] == comps:
            return layers[name]
    fitting = [a for a in layers.values() if a.shape[0] == comps]
    if len(fitting) == 1:
        return fitting[0]
    raise InputError(f"{path}: expected one {comps}-component image for {want}, found layers "
                     f"{', '.join(f'{k} ({v.shape[0]})' for k, v in layers.items()) or 'none'}")


def from_exr(path: str | os.PathLike, *, albedo: str | os.PathLike | None = None,
             normal: str | os.PathLike | None = None, depth: str | os.PathLike | None = None,
             spp: int | None = None) -> Inputs:
    """Read a (multi-layer) EXR plus optional single-feature files (see the module docstring).

    Layers outside the vocabulary are dropped, except a top-level image with no recognised name,
    which is taken as the radiance when the file has no other. A Blender Cycles file is read with
    its conventions (:mod:`mcdenoise.io.blender`: ``Combined`` when there is no ``Noisy Image``,
    world-space normals when the header gives the camera).
    """
    from mcdenoise.io import blender
    from mcdenoise.io.exr import read_exr, read_exr_header

    path = Path(path)
    layers = read_exr(path, spp=spp)
    header = read_exr_header(path)
    cycles = blender.is_cycles([c.name for c in header["channels"]])
    if cycles:
        layers = blender.apply_conventions(layers, header, path)
    if "radiance" not in layers and "image" in layers and layers["image"].shape[0] in (3, 4):
        layers["radiance"] = layers["image"][:3]
    if "radiance" not in layers and cycles:
        raise InputError(f"{path}: a Blender file with neither a 'Noisy Image' nor a 'Combined' pass: enable the "
                         f"Combined pass in View Layer Properties > Passes; layers: {', '.join(sorted(layers))}")
    if "radiance" not in layers:
        raise InputError(f"{path}: no colour (radiance) channels; layers: {', '.join(sorted(layers)) or 'none'}")
    h, w = layers["radiance"].shape[1:]
    inputs = Inputs(h, w, {}, paths=(path,), label=str(path), source="blender" if cycles else "")
    for name, arr in layers.items():
        if base_name(name) in CHANNELS:
            _add_pixels(inputs, name, arr, str(path))
    for want, extra, comps in (("albedo", albedo, 3), ("normal", normal, 3), ("depth", depth, 1)):
        if extra is None:
            continue
        p = Path(extra)
        arr = _image_layer(read_exr(p), p, want, comps)
        _add_pixels(inputs, want, arr, str(p))
        inputs.paths += (p,)
    return inputs


def from_folder(path: str | os.PathLike) -> Inputs:
    """Read an image folder of ``mcdenoise render``: ``noisy.exr`` whole, ``samples.bin`` lazily."""
    from mcdenoise.data.format import NOISY_FILE, SAMPLES_FILE, read_image
    from mcdenoise.io.exr import read_exr, read_exr_header
    from mcdenoise.io.names import group_channels

    folder = read_image(path)
    meta = folder.meta
    inputs = Inputs(meta.height, meta.width, {}, scene_features=meta.scene_feature_vector(),
                    paths=tuple(Path(path) / f for f in (NOISY_FILE, SAMPLES_FILE, "meta.json")), label=str(path))
    # read_exr, not folder.read_noisy: NaN/Inf are kept so that _add_pixels counts them.
    noisy = Path(path) / NOISY_FILE
    names = [c.name for c in read_exr_header(noisy)["channels"]]
    inputs.pixel_names = {n for n in group_channels(names, filename=noisy.name) if base_name(n) in CHANNELS}

    def load(inp: Inputs) -> None:
        for name, arr in read_exr(noisy, unknown="drop").items():
            if base_name(name) in CHANNELS:
                _add_pixels(inp, name, arr, str(noisy))

    inputs.loader = load
    if folder.samples is not None:
        inputs.samples = FolderSamples(folder.samples)
    return inputs


def from_arrays(color: np.ndarray, *, albedo: np.ndarray | None = None, normal: np.ndarray | None = None,
                depth: np.ndarray | None = None, features: dict[str, np.ndarray] | None = None,
                samples: dict[str, np.ndarray] | None = None,
                scene_features: np.ndarray | None = None) -> Inputs:
    """In-memory buffers, all channel-first float arrays: ``color`` (3, H, W) is the radiance."""
    if color.ndim != 3 or color.shape[0] != 3:
        raise InputError(f"color: expected (3, H, W), got shape {color.shape}")
    h, w = color.shape[1:]
    inputs = Inputs(h, w, {}, label="color")
    _add_pixels(inputs, "radiance", color, "color")
    for name, arr in (("albedo", albedo), ("normal", normal), ("depth", depth)):
        if arr is not None:
            _add_pixels(inputs, name, arr[None] if arr.ndim == 2 else arr, name)
    for name, arr in (features or {}).items():
        if base_name(name) not in CHANNELS:
            raise InputError(f"features: {name!r} is not in the channel vocabulary ({', '.join(sorted(CHANNELS))})")
        _add_pixels(inputs, name, arr[None] if arr.ndim == 2 else arr, f"features[{name!r}]")
    if samples:
        for name in samples:
            if base_name(name) not in CHANNELS:
                raise InputError(f"samples: {name!r} is not in the channel vocabulary")
        src = ArraySamples(samples)
        for name, arr in src.arrays.items():
            if arr.shape[-2:] != (h, w):
                raise InputError(f"size mismatch: samples[{name!r}] is {arr.shape[-1]}x{arr.shape[-2]} (WxH), "
                                 f"color is {w}x{h}")
        inputs.samples = src
    if scene_features is not None:
        sf = np.asarray(scene_features, np.float32).reshape(-1)
        if sf.shape != (len(SCENE_FEATURES),):
            raise InputError(f"scene_features: expected {len(SCENE_FEATURES)} values {SCENE_FEATURES}, got {sf.shape}")
        inputs.scene_features = sf
    return inputs
