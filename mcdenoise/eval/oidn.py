"""Intel Open Image Denoise as a baseline, through the ``oidn`` pip package (OIDN 1.4).

The package's Python layer has two traps we avoid here: it never sets the ``hdr`` flag (OIDN then
treats input as LDR and clamps it to [0, 1]), and it silently copies non-contiguous inputs into a
temporary that is freed before the filter runs (OIDN then reads garbage). We call the C API through
the package's library handle, keep every buffer contiguous and alive until the filter has run, and
check the device error after each call.
"""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from mcdenoise.errors import McDenoiseError

__all__ = ["oidn_available", "oidn_denoise", "OIDNError"]


class OIDNError(McDenoiseError):
    pass


def _lib() -> Any:
    try:
        import oidn  # noqa: F401  (loads libOpenImageDenoise with its bundled libtbb)
        import oidn.capi as capi
    except (ImportError, OSError) as e:  # OSError: libtbb12 missing
        raise OIDNError(f"Open Image Denoise is not usable: {e} (install the 'oidn' extra and Debian's libtbb12)") from e
    return capi


def oidn_available() -> bool:
    try:
        _lib()
    except OIDNError:
        return False
    return True


def _check(capi: Any, device: int, what: str) -> None:
    # The package binds oidnGetDeviceError(device, NULL); our own binding also gets the message.
    msg = ctypes.c_char_p()
    code = _error_fn()(ctypes.c_void_p(device), ctypes.byref(msg))
    if code != 0:
        text = msg.value.decode(errors="replace") if msg.value else "unknown error"
        raise OIDNError(f"OIDN {what} failed (code {code}): {text}")


_ERR_FN: Any = None
_SET_BOOL: Any = None


def _error_fn() -> Any:
    global _ERR_FN
    if _ERR_FN is None:
        import oidn

        lib = ctypes.CDLL(_library_path(oidn))
        fn = lib.oidnGetDeviceError
        fn.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_char_p)]
        fn.restype = ctypes.c_int
        _ERR_FN = fn
    return _ERR_FN


def _set_bool_fn() -> Any:
    global _SET_BOOL
    if _SET_BOOL is None:
        import oidn

        lib = ctypes.CDLL(_library_path(oidn))
        fn = lib.oidnSetFilter1b
        fn.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_bool]
        fn.restype = None
        _SET_BOOL = fn
    return _SET_BOOL


def _library_path(oidn_mod: Any) -> str:
    import glob
    import os

    here = os.path.dirname(oidn_mod.__file__)
    found = sorted(glob.glob(os.path.join(here, "lib.*", "libOpenImageDenoise.so*")))
    if not found:
        raise OIDNError(f"no libOpenImageDenoise found under {here}")
    return found[0]


def _hwc(x: np.ndarray | None, name: str, shape: tuple[int, int]) -> np.ndarray | None:
    if x is None:
        return None
    x = np.asarray(x, dtype=np.float32)
    if x.ndim != 3 or x.shape[0] != 3 or x.shape[1:] != shape:
        raise OIDNError(f"OIDN input {name!r}: expected (3, {shape[0]}, {shape[1]}), got {tuple(x.shape)}")
    return np.ascontiguousarray(np.moveaxis(x, 0, -1))


def oidn_denoise(
    color: np.ndarray,
    albedo: np.ndarray | None = None,
    normal: np.ndarray | None = None,
    *,
    hdr: bool = True,
    clean_aux: bool = False,
) -> np.ndarray:
    """Denoise ``color`` (3, H, W) linear radiance with OIDN's ``RT`` filter; returns (3, H, W).

    ``albedo`` and ``normal`` (3, H, W) are optional guides (normal needs albedo, as OIDN requires).
    ``hdr=True`` (default) keeps radiance above 1; set it False only for tonemapped LDR input.
    """
    capi = _lib()
    color = np.asarray(color)
    if color.ndim != 3 or color.shape[0] != 3:
        raise OIDNError(f"OIDN input 'color': expected (3, H, W), got {tuple(color.shape)}")
    h, w = color.shape[1:]
    if normal is not None and albedo is None:
        raise OIDNError("OIDN needs an albedo guide to use a normal guide")
    buffers = {"color": _hwc(color, "color", (h, w)), "albedo": _hwc(albedo, "albedo", (h, w)),
               "normal": _hwc(normal, "normal", (h, w))}
    out = np.zeros((h, w, 3), dtype=np.float32)
    device = capi.NewDevice(capi.DEVICE_TYPE_CPU)
    capi.CommitDevice(device)
    _check(capi, device, "device creation")
    filt = capi.NewFilter(device, "RT")
    try:
        for name, buf in buffers.items():
            if buf is not None:
                capi.SetSharedFilterImage(filt, name, buf, capi.FORMAT_FLOAT3, w, h)
        capi.SetSharedFilterImage(filt, "output", out, capi.FORMAT_FLOAT3, w, h)
        _set_bool_fn()(ctypes.c_void_p(filt), b"hdr", bool(hdr))
        if clean_aux:
            _set_bool_fn()(ctypes.c_void_p(filt), b"cleanAux", True)
        capi.CommitFilter(filt)
        _check(capi, device, "filter set-up")
        capi.ExecuteFilter(filt)
        _check(capi, device, "filter execution")
    finally:
        capi.ReleaseFilter(filt)
        capi.ReleaseDevice(device)
    del buffers  # kept alive until here on purpose: OIDN reads them during ExecuteFilter
    return np.ascontiguousarray(np.moveaxis(out, -1, 0))
