"""Data format v1: one image on disk, its per-sample store, and the one reader and writer.

One image is a folder::

    meta.json       ImageMeta + format version + which files exist
    samples.bin     per-sample buffers (optional): tiled, memory-mappable, JSON header
    noisy.exr       per-pixel mean <name> and variance of the mean <name>_variance per channel
    reference.exr   converged reference (optional): radiance, maybe diffuse/specular/albedo

``samples.bin`` layout (all little-endian)::

    0   8 bytes   magic b"MCDSAMPL"
    8   uint32    format version (1)
    12  uint32    0 (reserved)
    16  uint64    n = length of the JSON header in bytes
    24  n bytes   JSON header (UTF-8), padded with spaces up to the first data section
    then, for each channel at the page-aligned offset its header entry gives, an array of shape
    (tiles_y, tiles_x, spp, C, tile, tile) in its dtype (float32, or float16 for half_ok channels)

Pixel rows and columns are cut into ``tile x tile`` tiles (32 by default: 4 KiB per sample and
component in float32, one page); the image is zero-padded to whole tiles. A crop reads only the
tiles it overlaps and, within a tile, only the requested samples: every read is a contiguous run.
See docs/FORMAT.md for the full specification.
"""

from __future__ import annotations

import json
import math
import os
import struct
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.data.channels import (
    CHANNELS,
    SCENE_FEATURES,
    base_name,
    get_channel,
    is_variance_name,
    num_components,
    variance_name,
)
from mcdenoise.errors import FormatError
from mcdenoise.io.atomic import atomic_dir, atomic_file

__all__ = [
    "FORMAT_VERSION",
    "ImageMeta",
    "write_image",
    "SampleWriter",
    "SampleReader",
    "ImageFolder",
    "read_image",
    "pixel_stats",
    "check_finite",
    "SAMPLES_FILE",
    "NOISY_FILE",
    "REFERENCE_FILE",
    "META_FILE",
    "DEFAULT_TILE",
]

FORMAT_VERSION = 1
MAGIC = b"MCDSAMPL"
SAMPLES_FILE = "samples.bin"
NOISY_FILE = "noisy.exr"
REFERENCE_FILE = "reference.exr"
META_FILE = "meta.json"
DEFAULT_TILE = 32
_PAGE = 4096
_PREFIX = struct.Struct("<8sIIQ")  # magic, version, reserved, header length


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
        meta.channels = list(meta.channels)
        meta.validate(where)
        return meta

    def scene_feature_vector(self) -> np.ndarray:
        """``(len(SCENE_FEATURES),)`` float32 in SCENE_FEATURES order, 0 where absent."""
        return np.array([float(self.scene_features.get(k, 0.0)) for k in SCENE_FEATURES], np.float32)


# ----------------------------------------------------------------------------- helpers


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


def pixel_stats(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel mean and variance of the mean from ``(S, C, H, W)`` samples.

    variance of the mean = unbiased sample variance / S
                         = sum_s (x_s - mean)^2 / ((S - 1) * S);
    it is 0 when S == 1 (no estimate possible). Computed in float64, returned as float32 ``(C, H, W)``.
    """
    x = np.asarray(samples, dtype=np.float64)
    s = x.shape[0]
    mean = x.mean(axis=0)
    if s < 2:
        var = np.zeros_like(mean)
    else:
        var = ((x - mean) ** 2).sum(axis=0) / ((s - 1) * s)
    return mean.astype(np.float32), var.astype(np.float32)


def check_finite(
    name: str,
    arr: np.ndarray,
    path: str | os.PathLike,
    *,
    sanitize: bool = False,
    offset: tuple[int, int] = (0, 0),
    sample_index: Sequence[int] | None = None,
) -> np.ndarray:
    """Refuse (or, with ``sanitize``, zero with a warning) NaN/Inf in ``arr``.

    ``arr`` is ``(C, H, W)`` or ``(S, C, H, W)``; the report names the count and the first bad
    location in full-image coordinates (``offset`` = crop origin ``(y0, x0)``).
    """
    bad = ~np.isfinite(arr)
    n = int(bad.sum())
    if n == 0:
        return arr
    n_nan = int(np.isnan(arr).sum())
    first = np.unravel_index(int(np.argmax(bad)), arr.shape)
    comps = get_channel(name).components if base_name(name) in CHANNELS else None
    parts = []
    if arr.ndim == 4:
        s = first[0] if sample_index is None else sample_index[first[0]]
        parts.append(f"sample {s}")
        first = first[1:]
    c, y, x = (int(v) for v in first)
    parts.append(f"component {comps[c] if comps and c < len(comps) else c}")
    parts.append(f"pixel (y={y + offset[0]}, x={x + offset[1]})")
    msg = (f"channel {name!r}: {n} non-finite value(s) ({n_nan} NaN, {n - n_nan} Inf), "
           f"first at {', '.join(parts)}")
    if not sanitize:
        raise FormatError(path, msg + "; pass sanitize=True to replace them by 0")
    warnings.warn(f"{os.fspath(path)}: {msg}; replaced by 0", stacklevel=3)
    out = arr.copy()
    out[bad] = 0
    return out


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


# ----------------------------------------------------------------------------- writer


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
        overwrite: replace an existing folder (atomically) instead of refusing.
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        meta: ImageMeta,
        *,
        tile: int = DEFAULT_TILE,
        half: str | Sequence[str] = "auto",
        overwrite: bool = False,
    ) -> None:
        meta.validate(folder)
        if tile < 1:
            raise ValueError("tile must be >= 1")
        self.folder = Path(folder)
        self.meta = meta
        if self.folder.exists() and not overwrite:
            raise FileExistsError(f"{self.folder}: already exists (pass overwrite=True to replace it)")
        self.overwrite = overwrite
        self._ctx = atomic_dir(self.folder, overwrite=overwrite)
        self.tmp = self._ctx.__enter__()
        self.header, size = _samples_header(meta, tile, half)
        self.tile = tile
        path = self.tmp / SAMPLES_FILE
        with open(path, "wb") as f:
            text = json.dumps(self.header, indent=1).encode()
            f.write(_PREFIX.pack(MAGIC, FORMAT_VERSION, 0, len(text)))
            f.write(text)
            f.truncate(size)  # sparse: unwritten samples read as 0
        self._path = path
        self._sections = {e["name"]: e for e in self.header["channels"]}
        self._done = False

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
        if noisy is None:
            noisy = self.noisy_from_samples()
        if extra_noisy:
            clash = set(extra_noisy) & set(noisy)
            if clash:
                self.abort()
                raise ValueError(f"{self.folder}: extra_noisy repeats layers {sorted(clash)}")
            noisy = {**noisy, **extra_noisy}
        try:
            _write_rest(self.tmp, self.meta, noisy, reference, has_samples=True)
        except BaseException as exc:
            self._ctx.__exit__(type(exc), exc, exc.__traceback__)
            self._done = True
            raise
        self._done = True
        self._ctx.__exit__(None, None, None)
        return self.folder

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
    doc = {"format": "mcdenoise-image", "version": FORMAT_VERSION, **meta.to_json(),
           "files": {"samples": SAMPLES_FILE if has_samples else None, "noisy": NOISY_FILE,
                     "reference": REFERENCE_FILE if reference is not None else None}}
    with atomic_file(tmp / META_FILE) as t:
        t.write_text(json.dumps(doc, indent=1) + "\n")


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
        with atomic_dir(folder, overwrite=overwrite) as tmp:
            _write_rest(tmp, meta, noisy, reference, has_samples=False)
        return Path(folder)
    if list(samples) != list(meta.channels) and set(samples) != set(meta.channels):
        raise ValueError(f"{folder}: samples hold {sorted(samples)}, meta.channels says {sorted(meta.channels)}")
    for name, arr in samples.items():
        want = (meta.spp, num_components(name), meta.height, meta.width)
        if np.shape(arr) != want:
            raise ValueError(f"{folder}: samples[{name!r}] has shape {np.shape(arr)}, expected {want}")
    w = SampleWriter(folder, meta, tile=tile, half=half, overwrite=overwrite)
    try:
        for name, arr in samples.items():
            w.write(name, arr)
    except BaseException:
        w.abort()
        raise
    return w.finish(noisy=noisy, reference=reference)


# ----------------------------------------------------------------------------- reader


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

    def __init__(self, path: str | os.PathLike) -> None:
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
            text = f.read(n)
        if len(text) < n:
            raise FormatError(self.path, f"truncated: header needs {n} bytes, file has {size}")
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
    ) -> dict[str, np.ndarray]:
        """Read channels as name -> ``(s, C, h, w)`` float32.

        Args:
            channels: names to read (default: all).
            crop: ``(y0, x0, h, w)`` in pixels, inside the image (default: whole image).
            samples: a slice or a list of sample indices (any order, repeats allowed).
            sanitize: replace NaN/Inf by 0 with a warning instead of raising FormatError.
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
                        continue
                    for tx in range(tx0, tx1):
                        tile_off = row_off + tx * per_tile
                        for o, first, n in runs:
                            self._pread(fd, buf[ty - ty0, tx - tx0, o : o + n], tile_off + first * per_sample)
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


# ----------------------------------------------------------------------------- image folder


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
        self.meta = ImageMeta.from_json(doc, meta_path)
        files = doc.get("files", {})
        self._files = files
        self.cache = cache
        self._cache: dict[str, dict[str, np.ndarray]] = {}
        self.samples: SampleReader | None = None
        if files.get("samples"):
            self.samples = SampleReader(self.path / files["samples"])
            self.samples.meta = self.meta
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

