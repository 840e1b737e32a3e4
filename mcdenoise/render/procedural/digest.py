"""A digest of a scene dict that sees through Mitsuba objects, to compare two drawings."""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from mcdenoise.render._mitsuba import mitsuba

__all__ = ["scene_digest"]


def scene_digest(node: Any) -> str:
    """A hex digest of a scene dict that sees through Mitsuba objects (meshes, bitmaps,
    transforms), so two dicts drawn from the same seed can be compared."""
    h = hashlib.sha256()
    _digest(node, h)
    return h.hexdigest()


def _digest(node: Any, h: Any) -> None:
    mi = mitsuba()
    if isinstance(node, dict):
        h.update(b"{")
        for k in sorted(node):
            h.update(str(k).encode())
            _digest(node[k], h)
        h.update(b"}")
    elif isinstance(node, (list, tuple)):
        h.update(b"[")
        for v in node:
            _digest(v, h)
        h.update(b"]")
    elif isinstance(node, np.ndarray):
        h.update(np.ascontiguousarray(node).tobytes())
    elif isinstance(node, mi.Bitmap):
        h.update(np.ascontiguousarray(np.array(node)).tobytes())
    elif isinstance(node, mi.Mesh):
        params = mi.traverse(node)
        for key in ("vertex_positions", "faces", "vertex_texcoords"):
            h.update(np.array(params[key]).tobytes())
        h.update(str(node.bsdf()).encode())
    elif isinstance(node, mi.ScalarTransform4f):
        h.update(np.array(node.matrix, np.float64).tobytes())
    else:
        h.update(repr(node).encode())
