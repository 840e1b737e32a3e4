"""Exposure of a drawn scene's dict: every emitter's strength scaled by one factor."""

from __future__ import annotations

from typing import Any

__all__ = []


def _scale_emitters(node: Any, k: float) -> None:
    """Multiply the strength of every emitter plugin dict under ``node`` by ``k`` (in place)."""
    if not isinstance(node, dict):
        return
    t = node.get("type")
    if t == "area":
        node["radiance"]["value"] = [v * k for v in node["radiance"]["value"]]
    elif t in ("point", "spot"):
        node["intensity"]["value"] = [v * k for v in node["intensity"]["value"]]
    elif t == "envmap":
        node["scale"] = node.get("scale", 1.0) * k
    elif t == "sunsky":
        node["sun_scale"] = node.get("sun_scale", 1.0) * k
        node["sky_scale"] = node.get("sky_scale", 1.0) * k
    for v in node.values():
        _scale_emitters(v, k)
