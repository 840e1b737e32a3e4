"""``meta.json`` of one image folder (:class:`ImageMeta`), the format's file names and version,
and the one JSON reader every format document (meta.json, manifest.json, dataset.json) goes through."""

from __future__ import annotations

import json
import os
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.data.channels import CHANNELS, SCENE_FEATURES, base_name, is_variance_name
from mcdenoise.errors import FormatError

__all__ = ["FORMAT_VERSION", "ImageMeta", "read_json_document", "SAMPLES_FILE", "NOISY_FILE", "REFERENCE_FILE",
           "META_FILE", "DEFAULT_TILE", "META_CHECKSUM", "meta_crc32", "seal_meta", "check_meta_checksum"]

FORMAT_VERSION = 1
MAGIC = b"MCDSAMPL"
SAMPLES_FILE = "samples.bin"
NOISY_FILE = "noisy.exr"
REFERENCE_FILE = "reference.exr"
META_FILE = "meta.json"
DEFAULT_TILE = 32
#: The field of meta.json holding the CRC-32 of the rest of the document (see :func:`meta_crc32`).
META_CHECKSUM = "meta_crc32"


@dataclass
class ImageMeta:
    """What ``meta.json`` records about one image.

    Attributes:
        width, height: resolution in pixels.
        spp: samples per pixel of the per-sample / noisy data.
        channels: per-sample channel names (vocabulary names), in storage order. For an image
            without per-sample data: the channels of ``noisy.exr`` (without ``_variance``).
        scene: scene id (the unit of the train/val/test split).
        seed: sampler seed of the noisy render.
        renderer: provenance, e.g. ``"mitsuba 3.9.1 / mcdenoise 0.1.0"``.
        scene_features: keys from :data:`mcdenoise.data.channels.SCENE_FEATURES`.
        reference_spp: spp of ``reference.exr`` (None when unknown or absent).
        extra: free-form JSON-serialisable provenance (max_depth, frame index...).
    """

    width: int
    height: int
    spp: int
    channels: list[str]
    scene: str = ""
    seed: int = 0
    renderer: str = ""
    scene_features: dict[str, float] = field(default_factory=dict)
    reference_spp: int | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def validate(self, where: str | os.PathLike = "<ImageMeta>") -> None:
        """Raise FormatError (naming ``where``) when a field is out of range or unknown."""
        for key in ("width", "height", "spp"):
            v = getattr(self, key)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise FormatError(where, f"{key} must be a positive integer, got {v!r}")
        if not self.channels:
            raise FormatError(where, "no channels")
        if len(set(self.channels)) != len(self.channels):
            raise FormatError(where, f"duplicate channel names in {self.channels}")
        for name in self.channels:
            if base_name(name) not in CHANNELS or is_variance_name(name):
                raise FormatError(where, f"channel {name!r} is not in the channel vocabulary")
        for key in self.scene_features:
            if key not in SCENE_FEATURES:
                raise FormatError(where, f"unknown scene feature {key!r}; known: {', '.join(SCENE_FEATURES)}")
        if self.reference_spp is not None and (not isinstance(self.reference_spp, int) or self.reference_spp < 1):
            raise FormatError(where, f"reference_spp must be a positive integer or null, got {self.reference_spp!r}")

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["scene_features"] = {k: float(v) for k, v in self.scene_features.items()}
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any], where: str | os.PathLike = "<meta>") -> ImageMeta:
        names = {f for f in cls.__dataclass_fields__}
        missing = {"width", "height", "spp", "channels"} - set(d)
        if missing:
            raise FormatError(where, f"missing field(s) {sorted(missing)}")
        meta = cls(**{k: v for k, v in d.items() if k in names})
        # null (or otherwise mistyped) fields: one FormatError naming the field, not a TypeError.
        if not isinstance(meta.channels, list) or not all(isinstance(c, str) for c in meta.channels):
            raise FormatError(where, f"channels must be a list of names, got {meta.channels!r}")
        for key, typ in (("scene", str), ("renderer", str), ("scene_features", dict), ("extra", dict)):
            if not isinstance(getattr(meta, key), typ):
                raise FormatError(where, f"{key} must be a {typ.__name__}, got {getattr(meta, key)!r}")
        if not isinstance(meta.seed, int) or isinstance(meta.seed, bool):
            raise FormatError(where, f"seed must be an integer, got {meta.seed!r}")
        meta.validate(where)
        return meta

    def scene_feature_vector(self) -> np.ndarray:
        """``(len(SCENE_FEATURES),)`` float32 in SCENE_FEATURES order, 0 where absent."""
        return np.array([float(self.scene_features.get(k, 0.0)) for k in SCENE_FEATURES], np.float32)



def read_json_document(path: str | os.PathLike, fmt: str | None = None, what: str = "") -> dict[str, Any]:
    """Read a JSON object from ``path``; with ``fmt``, check its ``format`` and ``version`` fields.

    Every JSON file of the format (meta.json, manifest.json, dataset.json) is read through here, so
    each gives the same one-line :class:`FormatError` naming the file for corrupt JSON, a foreign
    file, or another format version.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(path, f"corrupt JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise FormatError(path, "not a JSON object")
    if fmt is not None:
        if doc.get("format") != fmt:
            raise FormatError(path, f"not an mcdenoise {what or fmt} (format field)")
        if doc.get("version") != FORMAT_VERSION:
            raise FormatError(path, f"format version {doc.get('version')}, this reader reads version {FORMAT_VERSION}")
    return doc


def meta_crc32(doc: dict[str, Any]) -> int:
    """CRC-32 of ``doc`` without its :data:`META_CHECKSUM` field, in a canonical JSON form (sorted
    keys, no spaces): any change to what a reader parses changes it, whitespace does not."""
    body = {k: v for k, v in doc.items() if k != META_CHECKSUM}
    return zlib.crc32(json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode())


def seal_meta(doc: dict[str, Any]) -> dict[str, Any]:
    """``doc`` with its :data:`META_CHECKSUM` field set (what the writer stores)."""
    return {**{k: v for k, v in doc.items() if k != META_CHECKSUM}, META_CHECKSUM: meta_crc32(doc)}


def check_meta_checksum(doc: dict[str, Any], path: str | os.PathLike) -> None:
    """Raise FormatError naming ``path`` unless ``doc`` carries a matching :data:`META_CHECKSUM`.

    A missing field is an error, not a skip: a damaged key must not switch verification off.
    """
    want = doc.get(META_CHECKSUM)
    if type(want) is not int:
        raise FormatError(path, f"damaged or written before meta.json carried its own checksum: no integer "
                                f"{META_CHECKSUM!r} field (render the image again)")
    if meta_crc32(doc) != want:
        raise FormatError(path, "damaged: the metadata does not match its own checksum (meta_crc32)")
