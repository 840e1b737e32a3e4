"""Multi-layer EXR read/write on the OpenEXR Python package, plus PNG previews.

Arrays are channel-first: a layer is ``(C, H, W)``; an EXR channel is ``(H, W)``. Layer names are
mapped to the channel vocabulary by the one rename table in :mod:`mcdenoise.io.names`.
"""

from __future__ import annotations

import contextlib
import io
import os
import struct
import tempfile
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.data.channels import CHANNELS, base_name, get_channel
from mcdenoise.errors import FormatError, OutputError
from mcdenoise.io.atomic import atomic_file
from mcdenoise.io.names import component_suffixes, group_channels, to_exr_channel_names

__all__ = [
    "read_exr",
    "read_exr_raw",
    "read_exr_header",
    "write_exr",
    "write_exr_raw",
    "write_preview",
    "tonemap",
    "TONEMAPS",
    "write_png",
]

TONEMAPS = ("srgb", "reinhard", "log")
#: White point of the ``log`` preview tonemap: log1p(x) / log1p(LOG_WHITE), clipped to [0, 1].
LOG_WHITE = 100.0


@contextlib.contextmanager
def _captured_stderr() -> Iterator[list[str]]:
    """Capture what the OpenEXR C library prints on fd 2 so that errors stay one line.

    Yields a list that receives the captured lines after the block.
    """
    lines: list[str] = []
    try:
        saved = os.dup(2)
    except OSError:  # no fd 2 (embedded interpreters): nothing to capture
        yield lines
        return
    # The Python binding also prints warnings through sys.stdout/sys.stderr.
    py_out, py_err = io.StringIO(), io.StringIO()
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            with contextlib.redirect_stdout(py_out), contextlib.redirect_stderr(py_err):
                yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace") + py_err.getvalue() + py_out.getvalue()
            lines.extend(ln for ln in text.splitlines() if ln.strip())


def _open_parts(path: Path, *, header_only: bool = False) -> list[Any]:
    """Every part of the file (a multi-part file, as Blender 5's File Output node writes one pass
    per part, has several), each checked for missing pixel data."""
    import OpenEXR

    if not path.is_file():
        raise FormatError(path, "no such file")
    problem = None
    parts: list[Any] = []
    with _captured_stderr() as lib_lines:
        try:
            f = OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
            parts = list(f.parts)
            if not parts:
                raise IndexError("no parts")
            if not header_only:
                for part in parts:
                    declared = {c.name for c in part.header["channels"]}
                    if set(part.channels) != declared:
                        problem = "pixel data missing (truncated or corrupt)"
        except (RuntimeError, IndexError, ValueError) as exc:
            problem = str(exc) or type(exc).__name__
            parts = []
    if problem is not None or not parts:
        detail = next((ln for ln in lib_lines if "EXR_ERR" in ln), lib_lines[0] if lib_lines else problem)
        # The library's message starts with the path again: keep only what follows it.
        detail = (detail or "").split(": ", 1)[-1] if detail and detail.startswith(str(path)) else detail
        raise FormatError(path, f"not a readable OpenEXR file (truncated or corrupt): {detail}")
    if len({tuple(np.asarray(w).ravel()) for w in (p.header.get("dataWindow") for p in parts) if w is not None}) > 1:
        raise FormatError(path, "its parts have different data windows (sizes); only one image per file is read")
    return parts


def _merged_channels(path: Path, parts: list[Any]) -> dict[str, Any]:
    """Channel name -> channel over every part; a name in two parts is refused."""
    out: dict[str, Any] = {}
    for part in parts:
        for name, ch in part.channels.items():
            if name in out:
                raise FormatError(path, f"channel {name!r} is in two parts of the file")
            out[name] = ch
    return out


def read_exr_header(path: str | os.PathLike) -> dict[str, Any]:
    """The header attributes of the first part (``channels``, ``dataWindow``, custom ones...);
    ``channels`` lists the channels of every part."""
    parts = _open_parts(Path(path), header_only=True)
    head = dict(parts[0].header)
    head["channels"] = [c for p in parts for c in p.header["channels"]]
    return head


def read_exr_raw(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """EXR channel name -> ``(H, W)`` array (of every part); half and float become float32, uint
    stays uint32."""
    out: dict[str, np.ndarray] = {}
    for name, ch in _merged_channels(Path(path), _open_parts(Path(path))).items():
        px = np.asarray(ch.pixels)
        if px.ndim != 2:
            raise FormatError(path, f"channel {name!r} has shape {px.shape}, expected (H, W)")
        out[name] = px.astype(np.float32) if px.dtype == np.float16 else px
    return out


def read_exr_file(path: str | os.PathLike) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header attributes (the first part's) and EXR channel name -> ``(H, W)`` array of every
    part in its stored pixel type (float16, float32, uint32): a file read to be written back
    unchanged (:func:`write_exr_file`; a multi-part file comes back as one part with every channel)."""
    parts = _open_parts(Path(path))
    head = {k: v for k, v in parts[0].header.items() if not (len(parts) > 1 and k in ("name", "type", "chunkCount"))}
    return head, {name: np.asarray(ch.pixels) for name, ch in _merged_channels(Path(path), parts).items()}


def write_exr_file(path: str | os.PathLike, channels: dict[str, np.ndarray], header: dict[str, Any]) -> Path:
    """Write ``channels`` in their own pixel types with the header attributes ``header`` (those
    of :func:`read_exr_file`, compression included; the channel list comes from ``channels``),
    atomically. Values are written bit for bit."""
    import OpenEXR

    data = {}
    for name, arr in channels.items():
        arr = np.asarray(arr)
        if arr.ndim != 2:
            raise ValueError(f"EXR channel {name!r}: expected (H, W), got shape {arr.shape}")
        if arr.dtype not in (np.float16, np.float32, np.uint32):
            arr = arr.astype(np.float32)
        data[name] = np.ascontiguousarray(arr)  # OpenEXR 3.5 writes strided arrays corrupted
    head: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    head.update({k: v for k, v in header.items() if k != "channels"})
    final = Path(path)
    with atomic_file(final) as tmp:
        try:
            OpenEXR.File(head, data).write(str(tmp))
        except RuntimeError as e:
            raise _write_error(final, e) from None
    return final


def read_exr(
    path: str | os.PathLike,
    *,
    spp: int | None = None,
    unknown: str = "keep",
) -> dict[str, np.ndarray]:
    """Layer name -> ``(C, H, W)`` float32, layer names mapped to the vocabulary.

    Args:
        path: any EXR written by us, Cycles, Mitsuba 3 (aov), pbrt-v4 (GBufferFilm) or OIDN-named.
        spp: samples per pixel, used to turn per-sample variances (pbrt ``Variance``) into our
            variance of the mean; without it they stay under their own name.
        unknown: what to do with layers outside the vocabulary: ``"keep"`` (under their EXR layer
            name; top-level channels that no scheme claims become ``"image"``), ``"drop"`` or
            ``"error"``.
    """
    path = Path(path)
    raw = read_exr_raw(path)
    groups = group_channels(list(raw), filename=path.name, spp=spp)
    out: dict[str, np.ndarray] = {}
    for layer, (pairs, scale) in groups.items():
        known = base_name(layer) in CHANNELS
        if not known:
            if unknown == "drop":
                continue
            if unknown == "error":
                raise FormatError(path, f"layer {layer!r} is not in the channel vocabulary")
        else:
            want = get_channel(layer).components
            have = [c for _, c in pairs]
            if have != list(want):
                raise FormatError(path, f"layer {layer!r} has components {have}, expected {list(want)}")
        arr = np.stack([raw[exr_name].astype(np.float32, copy=False) for exr_name, _ in pairs])
        out[layer] = arr * np.float32(scale) if scale != 1.0 else arr
    return out


def _check_layers(layers: dict[str, np.ndarray]) -> tuple[int, int]:
    shape = None
    for name, arr in layers.items():
        if arr.ndim != 3:
            raise ValueError(f"layer {name!r}: expected (C, H, W), got shape {arr.shape}")
        if shape is None:
            shape = arr.shape[1:]
        elif arr.shape[1:] != shape:
            raise ValueError(f"layer {name!r}: size {arr.shape[1:]} differs from {shape}")
    if shape is None:
        raise ValueError("no layers to write")
    return int(shape[0]), int(shape[1])


def write_exr_raw(
    path: str | os.PathLike,
    channels: dict[str, np.ndarray],
    *,
    half: Iterable[str] = (),
    attributes: dict[str, Any] | None = None,
) -> Path:
    """Write EXR channel name -> ``(H, W)`` as one ZIP-compressed scanline part, atomically.

    ``half`` lists EXR channel names stored as float16. ``attributes`` adds header attributes
    (str, int, float).
    """
    import OpenEXR

    half = set(half)
    data: dict[str, np.ndarray] = {}
    for name, arr in channels.items():
        arr = np.asarray(arr)
        if arr.ndim != 2:
            raise ValueError(f"EXR channel {name!r}: expected (H, W), got shape {arr.shape}")
        dtype = np.float16 if name in half else np.float32
        # OpenEXR 3.5 writes strided arrays corrupted: always hand it a C-contiguous copy.
        data[name] = np.ascontiguousarray(arr, dtype=dtype)
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(attributes or {})
    final = Path(path)
    with atomic_file(final) as tmp:
        try:
            OpenEXR.File(header, data).write(str(tmp))
        except RuntimeError as e:  # OpenEXR reports OS errors (read-only, disk full) as RuntimeError
            raise _write_error(final, e) from None
    return final


def _write_error(path: Path, exc: BaseException) -> OutputError:
    """One line for a failed OpenEXR write, with the OS reason when its message gives one."""
    text = " ".join(str(exc).split())
    low = text.lower()
    for needle, hint in (("no space", "the disk is full"), ("read-only", "the file system is read-only"),
                         ("permission denied", "permission denied"), ("quota", "the disk quota is exceeded")):
        if needle in low:
            return OutputError(path, f"writing failed: {hint}")
    return OutputError(path, f"writing failed: {text[:200] or type(exc).__name__}")


def write_exr(
    path: str | os.PathLike,
    layers: dict[str, np.ndarray],
    *,
    half: Iterable[str] = (),
    scheme: str = "mcdenoise",
    attributes: dict[str, Any] | None = None,
) -> Path:
    """Write layer -> ``(C, H, W)`` as a multi-layer EXR, atomically.

    Component suffixes come from the vocabulary (``radiance.R``, ``normal.X``, ``depth.Y``).
    ``half`` lists layers stored as float16; only vocabulary channels with ``half_ok`` (and their
    variances) may be. ``scheme`` writes another tool's names instead (see
    :mod:`mcdenoise.io.names`; ``oidn`` writes one layer per file, use
    :func:`mcdenoise.io.names.oidn_filename`).
    """
    _check_layers(layers)
    half = set(half)
    for name in half:
        if name not in layers:
            raise ValueError(f"half: no layer {name!r} to write")
        if base_name(name) in CHANNELS and not get_channel(name).half_ok:
            raise ValueError(f"layer {name!r} may overflow float16 (half_ok=False in the vocabulary)")
    channels: dict[str, np.ndarray] = {}
    half_names: list[str] = []
    for name, arr in layers.items():
        if scheme == "mcdenoise":
            names = [f"{name}.{c}" for c in component_suffixes(name, arr.shape[0])]
        else:
            names = to_exr_channel_names(name, arr.shape[0], scheme)
        for i, exr_name in enumerate(names):
            if exr_name in channels:
                raise ValueError(f"two layers write EXR channel {exr_name!r}")
            channels[exr_name] = arr[i]
            if name in half:
                half_names.append(exr_name)
    return write_exr_raw(path, channels, half=half_names, attributes=attributes)


def tonemap(rgb: np.ndarray, *, exposure: float = 0.0, kind: str = "srgb") -> np.ndarray:
    """Display values in [0, 1] from linear HDR ``(3, H, W)``.

    ``x = max(rgb, 0) * 2**exposure`` (NaN -> 0), then

    * ``srgb``: the sRGB transfer function of ``clip(x, 0, 1)``;
    * ``reinhard``: the sRGB transfer function of ``x / (1 + x)``;
    * ``log``: ``clip(log1p(x) / log1p(LOG_WHITE), 0, 1)`` with ``LOG_WHITE = 100`` (no sRGB curve).
    """
    if kind not in TONEMAPS:
        raise ValueError(f"unknown tonemap {kind!r}; choose one of {TONEMAPS}")
    x = np.nan_to_num(np.asarray(rgb, dtype=np.float64), nan=0.0, posinf=np.finfo(np.float32).max)
    x = np.maximum(x, 0.0) * (2.0 ** exposure)
    if kind == "log":
        return np.clip(np.log1p(x) / np.log1p(LOG_WHITE), 0.0, 1.0)
    y = x / (1.0 + x) if kind == "reinhard" else np.clip(x, 0.0, 1.0)
    return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1.0 / 2.4) - 0.055)


def write_png(path: str | os.PathLike, rgb8: np.ndarray) -> Path:
    """Write an 8-bit ``(H, W, 3)`` uint8 array as PNG (no dependency beyond zlib), atomically."""
    rgb8 = np.ascontiguousarray(rgb8, dtype=np.uint8)
    if rgb8.ndim != 3 or rgb8.shape[2] != 3:
        raise ValueError(f"expected (H, W, 3) uint8, got shape {rgb8.shape}")
    h, w, _ = rgb8.shape
    # Filter type 0 (none) per scanline.
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb8.reshape(h, w * 3)], axis=1).tobytes()

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    final = Path(path)
    with atomic_file(final) as tmp:
        tmp.write_bytes(png)
    return final


def preview_name(path_png: str | os.PathLike, exposure: float, kind: str) -> Path:
    """``out/noisy.png`` -> ``out/noisy_srgb_ev+0.0.png``: the name records tonemap and exposure."""
    p = Path(path_png)
    stem = p.name[:-4] if p.name.lower().endswith(".png") else p.name
    tag = f"_{kind}_ev{exposure:+.1f}"
    if not stem.endswith(tag):
        stem += tag
    return p.with_name(stem + ".png")


def write_preview(
    path_png: str | os.PathLike,
    rgb: np.ndarray,
    *,
    exposure: float = 0.0,
    tonemap: str = "srgb",
) -> Path:
    """Write linear ``(3, H, W)`` radiance as an 8-bit PNG; returns the path actually written.

    The file name records the tonemap and exposure (:func:`preview_name`), e.g.
    ``noisy_reinhard_ev+1.0.png``. See :func:`tonemap` for the curves.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[0] != 3:
        raise ValueError(f"preview: expected (3, H, W), got shape {rgb.shape}")
    disp = _tonemap(rgb, exposure=exposure, kind=tonemap)
    rgb8 = np.round(disp * 255.0).astype(np.uint8).transpose(1, 2, 0)
    return write_png(preview_name(path_png, exposure, tonemap), rgb8)


_tonemap = tonemap
