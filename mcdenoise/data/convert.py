"""Turn another renderer's EXR output (Cycles, Mitsuba aov, pbrt-v4, OIDN files) into an image folder.

The per-pixel buffers are read through the one rename table (:mod:`mcdenoise.io.names`), a Cycles
file with Blender's conventions (:mod:`mcdenoise.io.blender`: ``Combined`` is the colour where there
is no ``Noisy Image``, as in a reference rendered with the denoiser off); such an image has no
``samples.bin``, so only pixel models can use it.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.data.channels import CHANNELS, base_name, is_variance_name
from mcdenoise.data.format import ImageMeta, write_image
from mcdenoise.errors import FormatError
from mcdenoise.io import blender
from mcdenoise.io.exr import read_exr, read_exr_header
from mcdenoise.io.names import parse_oidn_filename

__all__ = ["read_renderer_exrs", "image_from_exr"]


def read_renderer_exrs(paths: Sequence[str | os.PathLike], *, spp: int | None = None) -> dict[str, np.ndarray]:
    """Vocabulary layers ``(C, H, W)`` from one or more EXRs of one image (e.g. OIDN's
    ``x_0008spp.hdr.exr`` + ``x_0008spp.alb.exr`` + ``x_0008spp.nrm.exr``); unknown layers are
    dropped. A layer found in two files is refused."""
    out: dict[str, np.ndarray] = {}
    size = None
    for p in paths:
        header = read_exr_header(p)
        if blender.is_cycles([c.name for c in header["channels"]]):
            layers = blender.apply_conventions(read_exr(p, spp=spp), header, Path(p))
            layers = {k: v for k, v in layers.items() if base_name(k) in CHANNELS}
        else:
            layers = read_exr(p, spp=spp, unknown="drop")
        for name, arr in layers.items():
            if name in out:
                raise FormatError(p, f"layer {name!r} was already read from another file of this image")
            if size is None:
                size = arr.shape[1:]
            elif arr.shape[1:] != size:
                raise FormatError(p, f"shape mismatch: layer {name!r} is {arr.shape[1]}x{arr.shape[2]}, "
                                     f"the other files are {size[0]}x{size[1]}")
            out[name] = arr
    if "radiance" not in out:
        raise FormatError(Path(paths[0]) if paths else "<no files>", "no radiance layer found in the given EXR file(s)")
    return out


def image_from_exr(
    noisy: Sequence[str | os.PathLike],
    folder: str | os.PathLike,
    *,
    spp: int | None = None,
    reference: Sequence[str | os.PathLike] = (),
    scene: str = "",
    renderer: str = "",
    overwrite: bool = False,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write an image folder (``noisy.exr``, ``reference.exr``, ``meta.json``) from renderer EXRs.

    ``spp`` defaults to the count in an OIDN file name (``_0008spp``) and is otherwise required.
    Variances are kept only where the source has them (e.g. pbrt's ``Variance`` / spp).
    """
    if spp is None:
        for p in noisy:
            parsed = parse_oidn_filename(p)
            if parsed is not None and parsed[1] is not None:
                spp = parsed[1]
                break
    if spp is None:
        raise ValueError("spp is not in the file names: pass spp=")
    layers = read_renderer_exrs(noisy, spp=spp)
    means = [n for n in layers if not is_variance_name(n)]
    ref = read_renderer_exrs(reference) if reference else None
    if ref is not None:
        ref = {k: v for k, v in ref.items() if not is_variance_name(k) and base_name(k) in CHANNELS}
    _, h, w = layers["radiance"].shape
    meta = ImageMeta(width=w, height=h, spp=spp, channels=means, scene=scene, renderer=renderer,
                     extra={"source": [os.fspath(p) for p in noisy], **(extra or {})})
    return write_image(folder, meta=meta, noisy=layers, reference=ref, overwrite=overwrite)
