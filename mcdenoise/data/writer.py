"""The writer of the data format: :class:`SampleWriter` (streamed per-sample store, finalised
atomically) and :func:`write_image` (one image folder from arrays)."""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.data.channels import CHANNELS, base_name, num_components, variance_name
from mcdenoise.data.meta import DEFAULT_TILE, FORMAT_VERSION, META_FILE, NOISY_FILE, REFERENCE_FILE, SAMPLES_FILE, ImageMeta, \
    seal_meta
from mcdenoise.data.samples_header import _PREFIX, MAGIC, _samples_header
from mcdenoise.data.checksums import ALGORITHM, block_crcs, file_crc32, header_crc32, table_offset
from mcdenoise.data.finite import sanitize_nonfinite
from mcdenoise.io.safety import (
    DEFAULT_MAX_BYTES,
    atomic_dir,
    atomic_file,
    check_output_path,
    check_space,
    is_mcdenoise_output,
    os_error,
)

__all__ = ["SampleWriter", "write_image"]


class SampleWriter:
    """Streaming writer of one image folder: memmap-backed per-sample store, finalised atomically.

    Fill the samples with :meth:`write` in any order (blocks of samples and/or rows), then call
    :meth:`finish`, which computes ``noisy.exr`` from the samples on disk (streamed in bands of
    tile rows) unless given, writes ``meta.json`` and renames the temporary folder into place.

    Args:
        folder: the image folder to create.
        meta: its metadata (``meta.channels`` are the per-sample channels).
        tile: tile edge in pixels.
        half: ``"auto"`` stores every ``half_ok`` channel as float16; or a list of channel names
            to store as float16 (each must be ``half_ok``); ``()`` for all float32.
        overwrite: replace an existing folder (atomically) instead of refusing; only a folder
            mcdenoise wrote (:func:`~mcdenoise.io.safety.is_mcdenoise_output`) is replaced.
        max_bytes: refuse (before allocating) an image larger than this (None = no cap); the
            free disk space is always checked.
        nonfinite: None stores samples as given (the readers report NaN/Inf); ``"sanitize"`` or
            ``"error"`` applies :func:`~mcdenoise.data.finite.sanitize_nonfinite` to everything
            written, counting replacements in :attr:`nonfinite`.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        meta: ImageMeta,
        *,
        tile: int = DEFAULT_TILE,
        half: str | Sequence[str] = "auto",
        overwrite: bool = False,
        max_bytes: int | None = DEFAULT_MAX_BYTES,
        nonfinite: str | None = None,
    ) -> None:
        meta.validate(folder)
        if tile < 1:
            raise ValueError("tile must be >= 1")
        self.folder = Path(folder)
        self.meta = meta
        self._done = True  # until the temporary folder exists: abort() has nothing to drop
        check_output_path(self.folder, overwrite=overwrite, replaceable=is_mcdenoise_output)
        self.overwrite = overwrite
        self.nonfinite_policy = nonfinite
        self.nonfinite = 0
        self.header, size = _samples_header(meta, tile, half)
        self.tile = tile
        self._table_offset = table_offset(size)
        n_blocks = len(meta.channels) * self.header["tiles"][0] * self.header["tiles"][1] * meta.spp
        total = self._table_offset + 4 * n_blocks
        check_space(self.folder, total + estimate_exr_bytes(meta), max_bytes=max_bytes,
                    what=f"a {meta.width}x{meta.height} image at {meta.spp} spp")
        self._ctx = atomic_dir(self.folder, overwrite=overwrite, replaceable=is_mcdenoise_output)
        self.tmp = self._ctx.__enter__()
        self._done = False
        path = self.tmp / SAMPLES_FILE
        self._path = path
        try:
            with open(path, "wb") as f:
                text = json.dumps(self.header, indent=1).encode()
                f.write(_PREFIX.pack(MAGIC, FORMAT_VERSION, 0, len(text)))
                f.write(text)
                f.truncate(total)  # unwritten samples read as 0
                # Reserve the blocks now: a sparse file on a disk that fills later faults the
                # memmap writes with SIGBUS (a crash with the temporary left behind).
                if hasattr(os, "posix_fallocate"):
                    os.posix_fallocate(f.fileno(), 0, total)
        except OSError as exc:
            self.abort()
            raise os_error(path, exc, "allocating samples.bin") from exc
        self._sections = {e["name"]: e for e in self.header["channels"]}

    def _map(self, name: str) -> np.memmap:
        """A fresh memmap of one channel's section.

        Mapped per call and dropped right after: a mapping kept open for the whole render keeps
        every written page in the process's RSS (7+ GiB at 1024x1024 x 64 spp), although the
        kernel could write them back and reclaim them.
        """
        e = self._sections[name]
        nty, ntx = self.header["tiles"]
        shape = (nty, ntx, self.meta.spp, len(e["components"]), self.tile, self.tile)
        return np.memmap(self._path, dtype=np.dtype(e["dtype"]).newbyteorder("<"), mode="r+",
                         offset=e["offset"], shape=shape)

    def write(self, name: str, data: np.ndarray, *, samples: slice = slice(None), rows: slice = slice(None)) -> None:
        """Store ``data`` ``(s, C, h, W)`` (full-width rows) at the given samples and rows."""
        if self._done:
            raise RuntimeError("SampleWriter.write after finish()")
        if name not in self._sections:
            raise KeyError(f"channel {name!r} is not in meta.channels {self.meta.channels}")
        if self.nonfinite_policy is not None:
            data, n = sanitize_nonfinite(np.asarray(data), self.nonfinite_policy, self.folder, f"channel {name!r}")
            self.nonfinite += n
        mm = self._map(name)
        s0, s1, sstep = samples.indices(self.meta.spp)
        y0, y1, ystep = rows.indices(self.meta.height)
        if sstep != 1 or ystep != 1:
            raise ValueError("samples and rows must be contiguous slices (step 1)")
        c = mm.shape[3]
        want = (s1 - s0, c, y1 - y0, self.meta.width)
        data = np.asarray(data)
        if data.shape != want:
            raise ValueError(f"channel {name!r}: expected data of shape {want} for samples "
                             f"{s0}:{s1}, rows {y0}:{y1}; got {data.shape}")
        t = self.tile
        ntx = mm.shape[1]
        pad_w = ntx * t - self.meta.width
        y = y0
        while y < y1:
            ty, r0 = divmod(y, t)
            r1 = min(t, r0 + (y1 - y))
            block = data[:, :, y - y0 : y - y0 + (r1 - r0), :]
            if pad_w:
                block = np.pad(block, ((0, 0), (0, 0), (0, 0), (0, pad_w)))
            # (s, C, r, ntx*T) -> (ntx, s, C, r, T)
            block = block.reshape(s1 - s0, c, r1 - r0, ntx, t).transpose(3, 0, 1, 2, 4)
            mm[ty, :, s0:s1, :, r0:r1, :] = block
            y += r1 - r0
        mm.flush()
        del mm

    def noisy_from_samples(self) -> dict[str, np.ndarray]:
        """Per-pixel ``name`` (mean) and ``name_variance`` (variance of the mean, see
        :func:`pixel_stats`) ``(C, H, W)`` of every channel, from the samples written so far,
        streamed one band of tile rows at a time."""
        h, w, s = self.meta.height, self.meta.width, self.meta.spp
        t = self.tile
        out: dict[str, np.ndarray] = {}
        chunk = 8  # samples per pass: bounds the float64 working set
        for name in self._sections:
            nty, ntx = self.header["tiles"]
            c = len(self._sections[name]["components"])
            mean = np.zeros((c, nty * t, ntx * t), np.float32)
            var = np.zeros_like(mean)
            for ty in range(nty):
                mm = self._map(name)  # re-mapped per band so read pages leave RSS with it
                # Shifted sums around sample 0 keep float64 sums of squares accurate.
                shift = np.asarray(mm[ty, :, 0], dtype=np.float64)  # (ntx, C, T, T)
                acc = np.zeros_like(shift)
                acc2 = np.zeros_like(shift)
                for k in range(0, s, chunk):
                    d = np.asarray(mm[ty, :, k : k + chunk], dtype=np.float64) - shift[:, None]
                    acc += d.sum(axis=1)
                    acc2 += (d * d).sum(axis=1)
                with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf samples: reported on read
                    m = acc / s
                    v = (acc2 - s * m * m) / ((s - 1) * s) if s > 1 else np.zeros_like(m)
                    v = np.maximum(v, 0.0)
                    m = m + shift
                # (ntx, C, T, T) -> (C, T, ntx*T)
                mean[:, ty * t : (ty + 1) * t] = m.transpose(1, 2, 0, 3).reshape(c, t, ntx * t)
                var[:, ty * t : (ty + 1) * t] = v.transpose(1, 2, 0, 3).reshape(c, t, ntx * t)
                del mm
            out[name] = np.ascontiguousarray(mean[:, :h, :w])
            out[variance_name(name)] = np.ascontiguousarray(var[:, :h, :w])
        return out

    def finish(
        self,
        *,
        noisy: dict[str, np.ndarray] | None = None,
        reference: dict[str, np.ndarray] | None = None,
        extra_noisy: dict[str, np.ndarray] | None = None,
    ) -> Path:
        """Write ``noisy.exr`` (computed from the samples when None), ``reference.exr``, ``meta.json``
        and move the folder into place. Returns the final folder.

        ``extra_noisy`` adds per-pixel-only layers ``(C, H, W)`` (e.g. ``position``, ``motion``) to
        the computed or given noisy buffers.
        """
        if self._done:
            raise RuntimeError("SampleWriter.finish called twice")
        try:
            if noisy is None:
                noisy = self.noisy_from_samples()
            if extra_noisy:
                clash = set(extra_noisy) & set(noisy)
                if clash:
                    raise ValueError(f"{self.folder}: extra_noisy repeats layers {sorted(clash)}")
                noisy = {**noisy, **extra_noisy}
            if self.nonfinite_policy is not None:
                noisy = self._sanitize_layers("noisy", noisy)
                reference = self._sanitize_layers("reference", reference)
                self.meta.extra["nonfinite_replaced"] = self.nonfinite
            checksums = self._write_block_table()
            _write_rest(self.tmp, self.meta, noisy, reference, has_samples=True, checksums=checksums)
        except OSError as exc:
            self._ctx.__exit__(type(exc), exc, exc.__traceback__)
            self._done = True
            raise os_error(self.folder, exc, "writing the image folder") from exc
        except BaseException as exc:
            self._ctx.__exit__(type(exc), exc, exc.__traceback__)
            self._done = True
            raise
        self._done = True
        self._ctx.__exit__(None, None, None)
        return self.folder

    def _sanitize_layers(self, what: str, layers: dict[str, np.ndarray] | None) -> dict[str, np.ndarray] | None:
        if layers is None:
            return None
        out = {}
        for k, v in layers.items():
            out[k], n = sanitize_nonfinite(np.asarray(v), self.nonfinite_policy or "sanitize", self.folder, f"{what} {k!r}")
            self.nonfinite += n
        return out

    def _write_block_table(self) -> dict[str, Any]:
        """CRC-32 of every (channel, tile, sample) block, appended to samples.bin (see
        :mod:`mcdenoise.data.checksums`); returns the ``checksums`` entry of meta.json."""
        table = np.stack([block_crcs(self._map(name)) for name in self._sections]).astype("<u4")
        raw = table.tobytes()
        with open(self._path, "r+b") as f:
            f.seek(self._table_offset)
            f.write(raw)
        return {"algorithm": ALGORITHM, "samples_blocks": {"offset": self._table_offset, "crc": zlib.crc32(raw)},
                "samples_header": header_crc32(self._path)}

    def abort(self) -> None:
        """Drop the temporary folder without writing anything."""
        if not self._done:
            self._done = True
            err = RuntimeError("aborted")
            try:
                self._ctx.__exit__(RuntimeError, err, None)
            except RuntimeError:
                pass

    def __enter__(self) -> SampleWriter:
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        if exc_type is not None:
            self.abort()
        elif not self._done:
            self.abort()
            raise RuntimeError("SampleWriter left without finish(): nothing was written")

    def __del__(self) -> None:  # a writer dropped without finish() leaves no temp folder behind
        try:
            self.abort()
        except Exception:
            pass


def estimate_exr_bytes(meta: ImageMeta) -> int:
    """Upper bound of noisy.exr + reference.exr for ``meta`` (float32, uncompressed): per-sample
    channels' mean and variance, a few per-pixel extras, and a 12-component reference."""
    comps = sum(num_components(c) for c in meta.channels)
    return 4 * meta.width * meta.height * (2 * comps + 8 + 12) + (1 << 20)


def _check_pixel_layers(where: str, layers: dict[str, np.ndarray], meta: ImageMeta) -> dict[str, np.ndarray]:
    out = {}
    for name, arr in layers.items():
        arr = np.asarray(arr, dtype=np.float32)
        if base_name(name) not in CHANNELS:
            raise ValueError(f"{where}: layer {name!r} is not in the channel vocabulary")
        want = (num_components(name), meta.height, meta.width)
        if arr.shape != want:
            raise ValueError(f"{where}: layer {name!r} has shape {arr.shape}, expected {want}")
        out[name] = arr
    return out


def _write_rest(
    tmp: Path,
    meta: ImageMeta,
    noisy: dict[str, np.ndarray],
    reference: dict[str, np.ndarray] | None,
    *,
    has_samples: bool,
    checksums: dict[str, Any] | None = None,
) -> None:
    from mcdenoise.io.exr import write_exr

    noisy = _check_pixel_layers("noisy", noisy, meta)
    missing = [c for c in meta.channels if c not in noisy]
    if missing:
        raise ValueError(f"noisy: no layer for channel(s) {missing} of meta.channels")
    attrs = {"mcdenoise_format_version": FORMAT_VERSION, "spp": meta.spp}
    write_exr(tmp / NOISY_FILE, noisy, attributes=attrs)
    if reference is not None:
        reference = _check_pixel_layers("reference", reference, meta)
        ref_attrs = {"mcdenoise_format_version": FORMAT_VERSION}
        if meta.reference_spp is not None:
            ref_attrs["spp"] = meta.reference_spp
        write_exr(tmp / REFERENCE_FILE, reference, attributes=ref_attrs)
    sums: dict[str, Any] = {"algorithm": ALGORITHM, **(checksums or {})}
    sums[NOISY_FILE] = file_crc32(tmp / NOISY_FILE)
    if reference is not None:
        sums[REFERENCE_FILE] = file_crc32(tmp / REFERENCE_FILE)
    doc = {"format": "mcdenoise-image", "version": FORMAT_VERSION, **meta.to_json(),
           "files": {"samples": SAMPLES_FILE if has_samples else None, "noisy": NOISY_FILE,
                     "reference": REFERENCE_FILE if reference is not None else None},
           "checksums": sums}
    with atomic_file(tmp / META_FILE) as t:
        t.write_text(json.dumps(seal_meta(doc), indent=1) + "\n")


def write_image(
    folder: str | os.PathLike,
    *,
    meta: ImageMeta,
    samples: dict[str, np.ndarray] | None = None,
    noisy: dict[str, np.ndarray] | None = None,
    reference: dict[str, np.ndarray] | None = None,
    overwrite: bool = False,
    tile: int = DEFAULT_TILE,
    half: str | Sequence[str] = "auto",
    max_bytes: int | None = DEFAULT_MAX_BYTES,
) -> Path:
    """Write one image folder atomically (a sibling temp folder, then a rename).

    Args:
        samples: name -> ``(S, C, H, W)``, exactly ``meta.channels``; optional.
        noisy: name or ``name_variance`` -> ``(C, H, W)``; computed from ``samples`` when None
            (see :func:`pixel_stats`); required when there are no samples.
        reference: name -> ``(C, H, W)``; optional.
    """
    meta.validate(folder)
    if samples is None:
        if noisy is None:
            raise ValueError(f"{folder}: need samples or noisy buffers")
        with atomic_dir(folder, overwrite=overwrite, replaceable=is_mcdenoise_output) as tmp:
            _write_rest(tmp, meta, noisy, reference, has_samples=False)
        return Path(folder)
    if list(samples) != list(meta.channels) and set(samples) != set(meta.channels):
        raise ValueError(f"{folder}: samples hold {sorted(samples)}, meta.channels says {sorted(meta.channels)}")
    for name, arr in samples.items():
        want = (meta.spp, num_components(name), meta.height, meta.width)
        if np.shape(arr) != want:
            raise ValueError(f"{folder}: samples[{name!r}] has shape {np.shape(arr)}, expected {want}")
    w = SampleWriter(folder, meta, tile=tile, half=half, overwrite=overwrite, max_bytes=max_bytes)
    try:
        for name, arr in samples.items():
            w.write(name, arr)
    except BaseException:
        w.abort()
        raise
    return w.finish(noisy=noisy, reference=reference)
