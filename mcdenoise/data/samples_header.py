"""The ``samples.bin`` prefix and JSON header: magic, version, per-channel dtype and page-aligned
offsets. Shared by the writer and the reader so both agree on the layout."""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Sequence
from typing import Any

import numpy as np

from mcdenoise.data.channels import get_channel, num_components
from mcdenoise.data.meta import FORMAT_VERSION, ImageMeta

MAGIC = b"MCDSAMPL"
_PAGE = 4096
_PREFIX = struct.Struct("<8sIIQ")  # magic, version, reserved, header length


def _dtype_for(name: str, half: str | Sequence[str]) -> str:
    if half == "auto":
        return "float16" if get_channel(name).half_ok else "float32"
    if name in half:
        if not get_channel(name).half_ok:
            raise ValueError(f"channel {name!r} may overflow float16 (half_ok=False in the vocabulary)")
        return "float16"
    return "float32"


def _samples_header(meta: ImageMeta, tile: int, half: str | Sequence[str]) -> tuple[dict[str, Any], int]:
    """The JSON header of ``samples.bin`` with page-aligned channel offsets, and the file size."""
    nty, ntx = math.ceil(meta.height / tile), math.ceil(meta.width / tile)
    entries = []
    for name in meta.channels:
        dt = _dtype_for(name, half)
        c = num_components(name)
        nbytes = nty * ntx * meta.spp * c * tile * tile * np.dtype(dt).itemsize
        entries.append({"name": name, "components": list(get_channel(name).components),
                        "dtype": dt, "offset": 0, "nbytes": nbytes})
    header = {
        "format": "mcdenoise-samples",
        "version": FORMAT_VERSION,
        "spp": meta.spp,
        "height": meta.height,
        "width": meta.width,
        "tile": tile,
        "tiles": [nty, ntx],
        "layout": "tiles_y, tiles_x, spp, components, tile, tile",
        "byteorder": "little",
        "channels": entries,
        "scene_features": {k: float(v) for k, v in meta.scene_features.items()},
        "provenance": {"scene": meta.scene, "seed": meta.seed, "renderer": meta.renderer},
    }
    data_start = _PAGE
    while True:
        off = data_start
        for e in entries:
            e["offset"] = off
            off += -(-e["nbytes"] // _PAGE) * _PAGE
        text = json.dumps(header, indent=1).encode()
        if _PREFIX.size + len(text) <= data_start:
            return header, off
        data_start += _PAGE

