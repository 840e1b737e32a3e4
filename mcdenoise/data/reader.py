"""The reader of ``samples.bin``: :class:`SampleReader` validates the header and size and reads
crops and sample subsets with one positional read per contiguous run."""

from __future__ import annotations

import json
import math
import os
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.data.checksums import read_table
from mcdenoise.data.channels import CHANNELS, base_name, get_channel, num_components
from mcdenoise.data.finite import check_finite
from mcdenoise.data.meta import FORMAT_VERSION, SAMPLES_FILE, ImageMeta
from mcdenoise.data.samples_header import _PREFIX, MAGIC
from mcdenoise.errors import FormatError

__all__ = ["SampleReader"]


def _runs(indices: Sequence[int]) -> list[tuple[int, int, int]]:
    """Split sample indices into runs of consecutive values: (output start, first index, length)."""
    runs: list[tuple[int, int, int]] = []
    for pos, idx in enumerate(indices):
        if runs and runs[-1][1] + runs[-1][2] == idx:
            o, f, n = runs[-1]
            runs[-1] = (o, f, n + 1)
        else:
            runs.append((pos, idx, 1))
    return runs


class SampleReader:
    """Reader of ``samples.bin``: validates the header and size, reads crops and sample subsets.

    :meth:`read` issues one positional read per contiguous run of bytes it needs (tile rows when
    all samples are read, else per tile and per run of consecutive samples) straight into the
    output buffer; :attr:`bytes_read` counts them. :meth:`memmap` exposes the raw tiled arrays.
    """

    def __init__(self, path: str | os.PathLike, *, header_crc: int | None = None) -> None:
        """``header_crc``: CRC-32 of the prefix and JSON header that meta.json records; checked
        before the header is interpreted (None: unchecked, a file opened without its meta.json)."""
        p = Path(path)
        self.path = p / SAMPLES_FILE if p.is_dir() else p
        if not self.path.is_file():
            raise FormatError(self.path, "no such file")
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            prefix = f.read(_PREFIX.size)
            if len(prefix) < _PREFIX.size:
                raise FormatError(self.path, f"truncated: {size} bytes, too short for the header")
            magic, version, _, n = _PREFIX.unpack(prefix)
            if magic != MAGIC:
                raise FormatError(self.path, f"not an mcdenoise samples file (magic {magic!r})")
            if version != FORMAT_VERSION:
                raise FormatError(self.path, f"format version {version}, this reader reads version {FORMAT_VERSION}")
            # Bound the length by the file size before reading: a damaged length must not allocate.
            if n > size - _PREFIX.size:
                raise FormatError(self.path, f"damaged or truncated: the header length says {n} bytes, "
                                             f"the file has {size}")
            text = f.read(n)
        if len(text) < n:
            raise FormatError(self.path, f"truncated: header needs {n} bytes, file has {size}")
        if header_crc is not None and zlib.crc32(text, zlib.crc32(prefix)) != header_crc:
            raise FormatError(self.path, "damaged: the header does not match its checksum in meta.json")
        try:
            self.header: dict[str, Any] = json.loads(text)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise FormatError(self.path, f"corrupt JSON header ({exc})") from None
        h = self.header
        try:
            self.spp = int(h["spp"])
            self.height = int(h["height"])
            self.width = int(h["width"])
            self.tile = int(h["tile"])
            self.tiles = (int(h["tiles"][0]), int(h["tiles"][1]))
            entries = h["channels"]
            self._entries = {e["name"]: e for e in entries}
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            raise FormatError(self.path, f"corrupt header: missing or bad field {exc}") from None
        if h.get("version") != FORMAT_VERSION:
            raise FormatError(self.path, f"header says version {h.get('version')}, expected {FORMAT_VERSION}")
        if self.tiles != (math.ceil(self.height / self.tile), math.ceil(self.width / self.tile)):
            raise FormatError(self.path, f"tile grid {self.tiles} does not cover {self.height}x{self.width}")
        try:
            self.channels: list[str] = [str(e["name"]) for e in entries]
            end = self._check_entries(entries)
        except (KeyError, TypeError, ValueError) as exc:
            raise FormatError(self.path, f"corrupt header: missing or bad channel field {exc}") from None
        if size < end:
            raise FormatError(self.path, f"truncated: {size} bytes, the header needs {end}")
        self.scene_features: dict[str, float] = dict(h.get("scene_features", {}))
        self.provenance: dict[str, Any] = dict(h.get("provenance", {}))
        self.bytes_read = 0
        self.meta: ImageMeta | None = None  # set by ImageFolder
        #: meta.json's ``checksums`` entry (set by ImageFolder); reads are verified against it.
        self.checksums: dict[str, Any] | None = None
        self._table: np.ndarray | None = None

    def block_table(self) -> np.ndarray | None:
        """uint32 ``(channels, tiles_y, tiles_x, spp)`` CRC-32 of every block, or None when the
        image records none (written before checksums, or opened without its meta.json)."""
        info = (self.checksums or {}).get("samples_blocks")
        if info is None:
            return None
        if self._table is None:
            shape = (len(self.channels), *self.tiles, self.spp)
            try:
                self._table = read_table(self.path, info, shape)
            except (ValueError, KeyError, TypeError) as exc:
                raise FormatError(self.path, f"damaged: {exc}") from None
        return self._table

    def _verify(self, name: str, block: np.ndarray, ty: int, tx: int, sample: int) -> None:
        table = self.block_table()
        if table is None:
            return
        if zlib.crc32(np.ascontiguousarray(block)) != int(table[self.channels.index(name), ty, tx, sample]):
            t = self.tile
            raise FormatError(self.path, f"damaged: checksum mismatch in channel {name!r}, sample {sample}, "
                                         f"tile at pixels y={ty * t}..{ty * t + t - 1}, x={tx * t}..{tx * t + t - 1}")

    def _check_entries(self, entries: list[dict[str, Any]]) -> int:
        """Validate the channel entries against the vocabulary; returns the end of the last section."""
        end = 0
        for e in entries:
            name = e["name"]
            if base_name(name) not in CHANNELS:
                raise FormatError(self.path, f"channel {name!r} is not in the channel vocabulary")
            c = len(e["components"])
            if c != num_components(name):
                raise FormatError(self.path, f"channel {name!r} has {c} components, the vocabulary says {num_components(name)}")
            if e["dtype"] not in ("float16", "float32"):
                raise FormatError(self.path, f"channel {name!r}: unsupported dtype {e['dtype']!r}")
            if e["dtype"] == "float16" and not get_channel(name).half_ok:
                raise FormatError(self.path, f"channel {name!r} stored as float16 but may overflow it")
            want = self.tiles[0] * self.tiles[1] * self.spp * c * self.tile ** 2 * np.dtype(e["dtype"]).itemsize
            if e["nbytes"] != want:
                raise FormatError(self.path, f"channel {name!r}: {e['nbytes']} bytes, shape needs {want}")
            if not isinstance(e["offset"], int) or e["offset"] < 0:
                raise FormatError(self.path, f"channel {name!r}: bad offset {e['offset']!r}")
            end = max(end, e["offset"] + e["nbytes"])
        return end

    def __repr__(self) -> str:
        return f"SampleReader({str(self.path)!r}, spp={self.spp}, {self.height}x{self.width}, channels={self.channels})"

    def _entry(self, name: str) -> dict[str, Any]:
        if name not in self._entries:
            raise FormatError(self.path, f"missing channel {name!r} (has: {', '.join(self.channels)})")
        return self._entries[name]

    def memmap(self, name: str) -> np.memmap:
        """Read-only memmap of channel ``name``: ``(tiles_y, tiles_x, spp, C, tile, tile)``."""
        e = self._entry(name)
        shape = (*self.tiles, self.spp, len(e["components"]), self.tile, self.tile)
        return np.memmap(self.path, dtype=np.dtype(e["dtype"]).newbyteorder("<"), mode="r",
                         offset=e["offset"], shape=shape)

    def _sample_indices(self, samples: slice | Sequence[int] | None) -> list[int]:
        if samples is None:
            return list(range(self.spp))
        if isinstance(samples, slice):
            return list(range(*samples.indices(self.spp)))
        idx = [int(i) for i in samples]
        for i in idx:
            if not 0 <= i < self.spp:
                raise IndexError(f"{self.path}: sample {i} out of range 0..{self.spp - 1}")
        return idx

    def read(
        self,
        channels: Sequence[str] | None = None,
        *,
        crop: tuple[int, int, int, int] | None = None,
        samples: slice | Sequence[int] | None = None,
        sanitize: bool = False,
        verify: bool = True,
    ) -> dict[str, np.ndarray]:
        """Read channels as name -> ``(s, C, h, w)`` float32.

        Args:
            channels: names to read (default: all).
            crop: ``(y0, x0, h, w)`` in pixels, inside the image (default: whole image).
            samples: a slice or a list of sample indices (any order, repeats allowed).
            sanitize: replace NaN/Inf by 0 with a warning instead of raising FormatError.
            verify: check every block read against the checksums meta.json records (a damaged
                block raises FormatError naming channel, sample and tile).
        """
        if isinstance(channels, str):
            raise TypeError(f"channels must be a list of names, got the string {channels!r}")
        names = list(self.channels if channels is None else channels)
        if crop is None:
            crop = (0, 0, self.height, self.width)
        y0, x0, hh, ww = (int(v) for v in crop)
        if hh < 1 or ww < 1 or y0 < 0 or x0 < 0 or y0 + hh > self.height or x0 + ww > self.width:
            raise ValueError(f"{self.path}: crop {crop} outside the {self.height}x{self.width} image")
        idx = self._sample_indices(samples)
        if not idx:
            raise ValueError(f"{self.path}: empty sample selection")
        runs = _runs(idx)
        t = self.tile
        ty0, ty1 = y0 // t, (y0 + hh - 1) // t + 1
        tx0, tx1 = x0 // t, (x0 + ww - 1) // t + 1
        ntx_all = self.tiles[1]
        whole_tiles = len(runs) == 1 and runs[0][1] == 0 and runs[0][2] == self.spp
        out: dict[str, np.ndarray] = {}
        fd = os.open(self.path, os.O_RDONLY)
        try:
            for name in names:
                e = self._entry(name)
                dt = np.dtype(e["dtype"]).newbyteorder("<")
                c = len(e["components"])
                per_sample = c * t * t * dt.itemsize
                per_tile = self.spp * per_sample
                buf = np.empty((ty1 - ty0, tx1 - tx0, len(idx), c, t, t), dt)
                for ty in range(ty0, ty1):
                    row_off = e["offset"] + (ty * ntx_all) * per_tile
                    if whole_tiles:
                        # All samples: the tiles tx0..tx1 of this tile row are one contiguous run.
                        self._pread(fd, buf[ty - ty0], row_off + tx0 * per_tile)
                        if verify:
                            for tx in range(tx0, tx1):
                                for s in range(self.spp):
                                    self._verify(name, buf[ty - ty0, tx - tx0, s], ty, tx, s)
                        continue
                    for tx in range(tx0, tx1):
                        tile_off = row_off + tx * per_tile
                        for o, first, n in runs:
                            self._pread(fd, buf[ty - ty0, tx - tx0, o : o + n], tile_off + first * per_sample)
                            if verify:
                                for k in range(n):
                                    self._verify(name, buf[ty - ty0, tx - tx0, o + k], ty, tx, first + k)
                full = buf.transpose(2, 3, 0, 4, 1, 5).reshape(len(idx), c, (ty1 - ty0) * t, (tx1 - tx0) * t)
                oy, ox = y0 - ty0 * t, x0 - tx0 * t
                arr = full[:, :, oy : oy + hh, ox : ox + ww].astype(np.float32)
                out[name] = check_finite(name, arr, self.path, sanitize=sanitize, offset=(y0, x0), sample_index=idx)
        finally:
            os.close(fd)
        return out

    def _pread(self, fd: int, view: np.ndarray, offset: int) -> None:
        mv = memoryview(view).cast("B")
        got = 0
        while got < len(mv):
            if hasattr(os, "preadv"):
                n = os.preadv(fd, [mv[got:]], offset + got)
            else:  # pragma: no cover - platforms without preadv
                chunk = os.pread(fd, len(mv) - got, offset + got)
                n = len(chunk)
                mv[got : got + n] = chunk
            if n == 0:
                raise FormatError(self.path, f"truncated: read past the end at byte {offset + got}")
            got += n
        self.bytes_read += got
