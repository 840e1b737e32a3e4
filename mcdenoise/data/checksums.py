"""Checksums of an image folder: CRC-32 per (channel, tile, sample) block of ``samples.bin``, of
its prefix and JSON header (``samples_header``), and per file for ``noisy.exr`` / ``reference.exr``,
recorded in ``meta.json`` under ``checksums``; meta.json covers itself (``meta_crc32``, see
:func:`mcdenoise.data.meta.meta_crc32`).

The block table is stored after the last channel section of ``samples.bin`` (at a page-aligned
offset that ``meta.json`` gives), as little-endian uint32 ``(channels, tiles_y, tiles_x, spp)`` in
header channel order. One block (``C x tile x tile`` values of one sample) is the smallest unit
the reader fetches, so every read can be verified exactly, without reading more than it needs.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ALGORITHM", "block_crcs", "file_crc32", "header_crc32", "read_table", "table_offset"]

ALGORITHM = "crc32"
_PAGE = 4096


def table_offset(data_end: int) -> int:
    """Byte offset of the block table: the first page boundary at or after the data sections."""
    return -(-data_end // _PAGE) * _PAGE


def block_crcs(mm: np.ndarray) -> np.ndarray:
    """CRC-32 of every ``(ty, tx, s)`` block of a channel section ``(tiles_y, tiles_x, spp, C, T, T)``
    as uint32 ``(tiles_y, tiles_x, spp)``. Reads the section one tile row at a time."""
    nty, ntx, spp = mm.shape[:3]
    out = np.empty((nty, ntx, spp), np.uint32)
    for ty in range(nty):
        row = np.ascontiguousarray(mm[ty])
        for tx in range(ntx):
            for s in range(spp):
                out[ty, tx, s] = zlib.crc32(row[tx, s])
    return out


def file_crc32(path: str | os.PathLike, chunk: int = 1 << 22) -> int:
    """CRC-32 of a whole file, streamed."""
    crc = 0
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                return crc
            crc = zlib.crc32(b, crc)


def header_crc32(path: str | os.PathLike) -> int:
    """CRC-32 of the prefix and JSON header of ``samples.bin`` (the writer's own file, trusted)."""
    from mcdenoise.data.samples_header import _PREFIX

    with open(path, "rb") as f:
        prefix = f.read(_PREFIX.size)
        n = _PREFIX.unpack(prefix)[3]
        return zlib.crc32(f.read(n), zlib.crc32(prefix))


def read_table(path: Path, info: dict[str, Any], shape: tuple[int, int, int, int]) -> np.ndarray:
    """The block table of ``samples.bin`` as uint32 ``shape``; raises ValueError when it does not
    match its own CRC recorded in meta.json (``info``) or is cut short."""
    n = int(np.prod(shape))
    with open(path, "rb") as f:
        f.seek(int(info["offset"]))
        raw = f.read(4 * n)
    if len(raw) != 4 * n:
        raise ValueError("the checksum table is cut short (truncated file)")
    if zlib.crc32(raw) != int(info["crc"]):
        raise ValueError("the checksum table itself is damaged")
    return np.frombuffer(raw, dtype="<u4").reshape(shape)
