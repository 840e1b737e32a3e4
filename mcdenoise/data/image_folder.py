"""One image folder on disk, read lazily: :class:`ImageFolder` and :func:`read_image`."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.data.checksums import file_crc32
from mcdenoise.data.finite import check_finite
from mcdenoise.data.checksums import ALGORITHM
from mcdenoise.data.meta import META_FILE, ImageMeta, check_meta_checksum, read_json_document
from mcdenoise.data.reader import SampleReader
from mcdenoise.errors import FormatError

__all__ = ["ImageFolder", "read_image"]


def _checksums(doc: dict[str, Any], files: dict[str, Any], where: Path) -> dict[str, Any]:
    """meta.json's ``checksums``, with an entry for every file it lists: a missing one is an error
    (a damaged key must not switch verification off)."""
    sums = doc.get("checksums")
    if not isinstance(sums, dict) or sums.get("algorithm") != ALGORITHM:
        raise FormatError(where, f"no checksums (an object with algorithm {ALGORITHM!r}); damaged or not ours")
    need = [files[k] for k in ("noisy", "reference") if files.get(k)]
    need += ["samples_header"] if files.get("samples") else []
    for key in need:
        if type(sums.get(key)) is not int:
            raise FormatError(where, f"no checksum for {key} (damaged)")
    blocks = sums.get("samples_blocks")
    if files.get("samples") and not (isinstance(blocks, dict) and type(blocks.get("offset")) is int
                                     and type(blocks.get("crc")) is int):
        raise FormatError(where, "no checksum table entry samples_blocks (damaged)")
    return sums


class ImageFolder:
    """One image on disk (see module docstring). Reading is lazy; nothing is cached unless ``cache``."""

    def __init__(self, path: str | os.PathLike, *, cache: bool = False) -> None:
        self.path = Path(path)
        meta_path = self.path / META_FILE
        if not self.path.is_dir():
            raise FormatError(self.path, "no such image folder")
        if not meta_path.is_file():
            raise FormatError(meta_path, "no such file (not an image folder?)")
        doc = read_json_document(meta_path, "mcdenoise-image", "image meta.json")
        check_meta_checksum(doc, meta_path)
        self.meta = ImageMeta.from_json(doc, meta_path)
        files = doc.get("files", {})
        if not isinstance(files, dict):
            raise FormatError(meta_path, f"files must be an object, got {files!r}")
        self._files = files
        self.checksums: dict[str, Any] = _checksums(doc, files, meta_path)
        self.cache = cache
        self._cache: dict[str, dict[str, np.ndarray]] = {}
        self.samples: SampleReader | None = None
        if files.get("samples"):
            self.samples = SampleReader(self.path / files["samples"], header_crc=self.checksums["samples_header"])
            self.samples.meta = self.meta
            self.samples.checksums = self.checksums
            r0, blocks = self.samples, self.checksums["samples_blocks"]
            end = blocks["offset"] + 4 * len(r0.channels) * r0.tiles[0] * r0.tiles[1] * r0.spp
            size = r0.path.stat().st_size
            if size < end:
                raise FormatError(r0.path, f"truncated: {size} bytes, the data and its checksums need {end}")
            r = self.samples
            if (r.spp, r.height, r.width) != (self.meta.spp, self.meta.height, self.meta.width):
                raise FormatError(r.path, f"shape mismatch: spp/height/width {r.spp}/{r.height}/{r.width}, "
                                          f"meta.json says {self.meta.spp}/{self.meta.height}/{self.meta.width}")
            if r.channels != self.meta.channels:
                raise FormatError(r.path, f"channels {r.channels} differ from meta.json {self.meta.channels}")
        self.has_reference = bool(files.get("reference"))
        if self.has_reference and not (self.path / files["reference"]).is_file():
            raise FormatError(self.path / files["reference"], "no such file (meta.json lists it)")

    def __repr__(self) -> str:
        return f"ImageFolder({str(self.path)!r}, {self.meta.width}x{self.meta.height}, spp={self.meta.spp})"

    @property
    def scene(self) -> str:
        return self.meta.scene

    def _read_pixels(self, key: str, channels: Sequence[str] | None,
                     crop: tuple[int, int, int, int] | None, sanitize: bool) -> dict[str, np.ndarray]:
        from mcdenoise.io.exr import read_exr

        path = self.path / self._files[key]
        layers = self._cache.get(key)
        if layers is None:
            layers = read_exr(path, unknown="error")
            for name, arr in layers.items():
                if arr.shape[1:] != (self.meta.height, self.meta.width):
                    raise FormatError(path, f"shape mismatch: layer {name!r} is {arr.shape[1]}x{arr.shape[2]}, "
                                            f"meta.json says {self.meta.height}x{self.meta.width}")
            if key == "noisy":
                for name in self.meta.channels:
                    if name not in layers:
                        raise FormatError(path, f"missing channel {name!r} listed in meta.json (has: {', '.join(sorted(layers))})")
            # After the structural checks, which name the problem more precisely than a mismatch.
            self._verify_file(path)
            if self.cache:
                self._cache[key] = layers
        if isinstance(channels, str):
            raise TypeError(f"channels must be a list of names, got the string {channels!r}")
        names = list(layers) if channels is None else list(channels)
        y0, x0, hh, ww = crop if crop is not None else (0, 0, self.meta.height, self.meta.width)
        if hh < 1 or ww < 1 or y0 < 0 or x0 < 0 or y0 + hh > self.meta.height or x0 + ww > self.meta.width:
            raise ValueError(f"{path}: crop {crop} outside the {self.meta.height}x{self.meta.width} image")
        out = {}
        for name in names:
            if name not in layers:
                raise FormatError(path, f"missing channel {name!r} (has: {', '.join(sorted(layers))})")
            arr = layers[name][:, y0 : y0 + hh, x0 : x0 + ww]
            out[name] = check_finite(name, np.array(arr, dtype=np.float32), path, sanitize=sanitize, offset=(y0, x0))
        return out

    def _verify_file(self, path: Path) -> None:
        """Compare a whole file with the CRC-32 meta.json records for it (when it records one)."""
        want = self.checksums.get(path.name)
        if type(want) is not int:
            raise FormatError(self.path / META_FILE, f"no checksum for {path.name} (damaged)")
        try:
            got = file_crc32(path)
        except FileNotFoundError:
            raise FormatError(path, "no such file (meta.json lists it)") from None
        if got != int(want):
            raise FormatError(path, "damaged: checksum mismatch (the file changed after it was written)")

    def read_noisy(self, channels: Sequence[str] | None = None, crop: tuple[int, int, int, int] | None = None,
                   *, sanitize: bool = False) -> dict[str, np.ndarray]:
        """Per-pixel buffers name -> ``(C, h, w)`` float32: means and ``*_variance`` (variance of the
        mean). ``channels=None`` returns every layer; otherwise exactly the names asked for."""
        return self._read_pixels("noisy", channels, crop, sanitize)

    def read_reference(self, channels: Sequence[str] | None = None, crop: tuple[int, int, int, int] | None = None,
                       *, sanitize: bool = False) -> dict[str, np.ndarray] | None:
        """Reference buffers name -> ``(C, h, w)`` float32, or None when the image has none."""
        if not self.has_reference:
            return None
        return self._read_pixels("reference", channels, crop, sanitize)


def read_image(folder: str | os.PathLike, *, cache: bool = False) -> ImageFolder:
    """Open one image folder (validates meta.json and the samples header; reads no pixels)."""
    return ImageFolder(folder, cache=cache)

