"""Intel Open Image Denoise 2.5.1 as a baseline, through the ``pyoidn`` package (2.5.1.0).

The wheel bundles ``libOpenImageDenoise`` 2.5.1 and its own TBB (found through the library's
RPATH), so no system package is needed. Its one-call ``pyoidn.denoise`` takes ``(H, W, 3)``
float16/float32 images, copies non-contiguous ones, keeps every bound buffer alive until the next
call and checks the device error after each step. What this module adds:

* our layout, ``(3, H, W)`` like every other image in the package, and any real dtype (float64
  from numpy arithmetic is common; pyoidn refuses it with a TypeError);
* ``hdr=True`` by default: pyoidn's default is ``hdr=False``, in which mode OIDN treats input as
  LDR and clamps it to [0, 1] -- silently wrong for radiance;
* shape checks that name the expected shape, and one error type (:class:`OIDNError`) with a
  one-line message for every failure, including OIDN's own ("unsupported combination of input
  features" becomes "normal needs albedo");
* :func:`version`, read from the loaded library, so reports say which OIDN produced a number;
* ``prefilter=``: OIDN's documented best-quality mode for noisy guides -- denoise albedo and normal
  with OIDN on their own first, then the colour with ``cleanAux`` (:func:`oidn_prefilter`).

pyoidn keeps one CPU device and filter per process and serialises calls, so this is safe from
threads; that device uses every core (OIDN's default), and threaded runs are not bitwise
repeatable (see ``tests/test_oidn.py``). ``threads=N`` runs on a device of its own committed with
OIDN's ``numThreads`` parameter (one per count, kept for the process), so a timing can give OIDN
the thread count torch has (``mcdenoise eval --threads N``).
"""

from __future__ import annotations

import atexit
import functools
import threading
from typing import Any

import numpy as np

from mcdenoise.errors import McDenoiseError

__all__ = ["OIDNError", "QUALITIES", "oidn_available", "oidn_denoise", "oidn_prefilter", "parse_quality", "device_threads", "version"]

#: OIDN's quality presets, best and slowest first; ``high`` is OIDN's default.
QUALITIES: tuple[str, ...] = ("high", "balanced", "fast")

#: Suffix of a quality name (``high-pf``) asking for guides prefiltered by OIDN ``fast`` first.
PREFILTERED_SUFFIX = "-pf"


def parse_quality(spec: str) -> tuple[str, str | None]:
    """``"high"`` -> ``("high", None)``; ``"high-pf"`` -> ``("high", "fast")``: the quality and the
    ``prefilter`` of :func:`oidn_denoise`, as every command spells them."""
    quality = spec.removesuffix(PREFILTERED_SUFFIX)
    if quality not in QUALITIES:
        raise OIDNError(f"OIDN quality {spec!r}: expected one of {', '.join(QUALITIES)}, each optionally with "
                        f"{PREFILTERED_SUFFIX} (guides prefiltered by OIDN fast first)")
    return quality, ("fast" if spec.endswith(PREFILTERED_SUFFIX) else None)


_INSTALL_HINT = "install it with: pip install 'pyoidn==2.5.1.0' (or mcdenoise's 'oidn' extra)"


class OIDNError(McDenoiseError):
    """Open Image Denoise is missing, was given bad input, or reported a failure."""


def _pyoidn() -> Any:
    """The imported ``pyoidn`` module, with its shared library loaded and a CPU device usable."""
    try:
        import pyoidn
    except ImportError as e:
        raise OIDNError(f"Open Image Denoise is not installed ({e}); {_INSTALL_HINT}") from e
    try:
        # pyoidn loads the shared library lazily; this first C call surfaces a broken install.
        cpu_ok = bool(pyoidn.Device.is_cpu_available())
    except OSError as e:  # dlopen failure: a wheel for another platform, a missing libstdc++
        raise OIDNError(f"Open Image Denoise library could not be loaded: {e}") from e
    if not cpu_ok:
        raise OIDNError("Open Image Denoise has no CPU device on this machine (it needs SSE4.1 or NEON)")
    return pyoidn


def oidn_available() -> bool:
    """True when :func:`oidn_denoise` can run here."""
    try:
        _pyoidn()
    except OIDNError:
        return False
    return True


@functools.lru_cache(maxsize=1)
def version() -> str:
    """The version of the loaded OIDN library, e.g. ``"2.5.1"`` (not the pip package's version)."""
    pyoidn = _pyoidn()
    device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
    try:
        packed = int(device.get_int("version"))  # OIDN packs it as major*10000 + minor*100 + patch
    finally:
        device.release()
    if packed <= 0:
        raise OIDNError(f"Open Image Denoise reported no version (got {packed})")
    return f"{packed // 10000}.{packed // 100 % 100}.{packed % 100}"


class _Pinned:
    """A CPU device committed with ``numThreads``, its RT filter, and the images bound last."""

    def __init__(self, pyoidn: Any, threads: int) -> None:
        self.device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        self.device.set_int("numThreads", int(threads))
        self.device.commit()
        self._check("device commit")
        self.filter = pyoidn.Filter(self.device, pyoidn.OIDN_FILTER_TYPE_RT)
        self._check("filter creation")
        self.bound: dict[str, np.ndarray] = {}  # shared with OIDN: kept alive until replaced

    def _check(self, step: str) -> None:
        msg = self.device.get_error()
        if msg:
            raise RuntimeError(f"{step}: {msg}")

    def run(self, pyoidn: Any, images: dict[str, np.ndarray], hdr: bool, clean_aux: bool, quality: str) -> None:
        """Bind ``images`` (``color`` or one guide alone, plus ``output``), set the parameters, execute."""
        flt = self.filter
        for name in self.bound:
            if name not in images:
                flt.unset_image(name)
        for name, arr in images.items():
            flt.set_image(name, arr, pyoidn.OIDN_FORMAT_FLOAT3)
        self.bound = images
        flt.set_bool("hdr", hdr)
        flt.set_bool("cleanAux", clean_aux)
        flt.set_quality({"high": pyoidn.OIDN_QUALITY_HIGH, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                         "fast": pyoidn.OIDN_QUALITY_FAST}[quality])
        flt.commit()
        self._check("filter commit")
        flt.execute()
        self._check("filter execution")

    def release(self) -> None:
        self.filter.release()
        self.device.release()


_PINNED: dict[int, _Pinned] = {}
_PINNED_LOCK = threading.Lock()


@atexit.register
def _release_pinned() -> None:
    with _PINNED_LOCK:
        for p in _PINNED.values():
            p.release()
        _PINNED.clear()


def _pinned(pyoidn: Any, threads: int) -> _Pinned:
    if threads not in _PINNED:
        _PINNED[threads] = _Pinned(pyoidn, threads)
    return _PINNED[threads]


def device_threads(threads: int | None = None) -> int:
    """The thread count OIDN's CPU device runs with: ``threads`` when given (after committing a
    device with it), else that of a default device (every core OIDN sees)."""
    pyoidn = _pyoidn()
    if threads is not None:
        with _PINNED_LOCK:
            return int(_pinned(pyoidn, threads).device.get_int("numThreads"))
    device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
    try:
        device.commit()
        return int(device.get_int("numThreads"))
    finally:
        device.release()


def _hwc(x: Any, name: str, shape: tuple[int, int] | None) -> np.ndarray:
    """``x`` (3, H, W), any real dtype, any strides -> contiguous float32 (H, W, 3)."""
    arr = np.asarray(x)
    want = "(3, H, W)" if shape is None else f"(3, {shape[0]}, {shape[1]})"
    if arr.ndim != 3 or arr.shape[0] != 3 or (shape is not None and arr.shape[1:] != shape):
        raise OIDNError(f"OIDN input {name!r}: expected {want}, got {tuple(arr.shape)}")
    if arr.shape[1] == 0 or arr.shape[2] == 0:
        raise OIDNError(f"OIDN input {name!r}: empty image {tuple(arr.shape)}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise OIDNError(f"OIDN input {name!r}: expected a real-valued array, got dtype {arr.dtype}")
    return np.ascontiguousarray(np.moveaxis(arr, 0, -1), dtype=np.float32)


def _run_guide(pyoidn: Any, name: str, guide: np.ndarray, quality: str, threads: int | None) -> np.ndarray:
    """(H, W, 3) guide -> (H, W, 3) OIDN-denoised guide (the RT filter with only that image set)."""
    out = np.empty_like(guide)
    try:
        with _PINNED_LOCK:
            # numThreads 0 is OIDN's "every core", the shared device's setting
            _pinned(pyoidn, 0 if threads is None else threads).run(pyoidn, {name: guide, "output": out}, False, False, quality)
    except (RuntimeError, ValueError, TypeError) as e:
        msg = " ".join(str(e).split())
        raise OIDNError(f"OIDN {version()} failed prefiltering {name}: {msg}") from e
    if name == "normal":  # OIDN's normal filter output is not re-normalised; keep [-1, 1]
        np.clip(out, -1.0, 1.0, out=out)
    return out


def oidn_prefilter(guide: Any, kind: str, *, quality: str = "fast", threads: int | None = None) -> np.ndarray:
    """Denoise one guide (3, H, W) -- ``kind`` ``"albedo"`` or ``"normal"`` -- with OIDN alone.

    Returns (3, H, W) float32; normals stay in [-1, 1].
    """
    if kind not in ("albedo", "normal"):
        raise OIDNError(f"OIDN prefilters albedo or normal guides, not {kind!r}")
    if quality not in QUALITIES:
        raise OIDNError(f"OIDN prefilter quality {quality!r}: expected one of {', '.join(QUALITIES)}")
    out = _run_guide(_pyoidn(), kind, _hwc(guide, kind, None), quality, threads)
    return np.ascontiguousarray(np.moveaxis(out, -1, 0))


def oidn_denoise(
    color: Any,
    albedo: Any | None = None,
    normal: Any | None = None,
    *,
    hdr: bool = True,
    quality: str = "high",
    clean_aux: bool = False,
    threads: int | None = None,
    prefilter: str | None = None,
) -> np.ndarray:
    """Denoise ``color`` (3, H, W) linear radiance with OIDN's ``RT`` filter.

    Args:
        color: (3, H, W) noisy radiance, non-negative; numpy array or CPU tensor, any real dtype.
        albedo: optional (3, H, W) guide in [0, 1].
        normal: optional (3, H, W) guide in [-1, 1]; OIDN accepts it only together with albedo.
        hdr: keep radiance above 1 (default). False only for tonemapped LDR input: OIDN then
            clamps to [0, 1].
        quality: one of :data:`QUALITIES`. ``fast`` took 1/1.85 of ``high``'s time at 1920x1080
            with both guides on 2 cores, with 1.9x the relMSE on a synthetic image
            (``benchmarks/bench_oidn.py quality``). On the CPU device
            ``balanced`` gives ``high``'s exact pixels except with ``clean_aux`` and both guides
            (OIDN 2.3+ uses a larger prefilter there).
        clean_aux: the guides are noise-free (e.g. from a reference render); OIDN then skips
            its own prefiltering of them.
        threads: run on a CPU device limited to this many threads (default: pyoidn's shared
            device, every core).
        prefilter: denoise the guides with OIDN at this quality first (:func:`oidn_prefilter`)
            and pass them as clean (``clean_aux``): OIDN's documented highest-quality mode for
            noisy guides (depth of field, motion blur, glossy paths). Costs one extra OIDN run
            per guide (``fast``: about 0.55x a ``high`` colour run each).

    Returns:
        (3, H, W) float32 denoised radiance, a new contiguous array.
    """
    pyoidn = _pyoidn()
    if quality not in QUALITIES:
        raise OIDNError(f"OIDN quality {quality!r}: expected one of {', '.join(QUALITIES)}")
    if normal is not None and albedo is None:
        raise OIDNError("OIDN needs an albedo guide to use a normal guide")
    rgb = _hwc(color, "color", None)
    shape = rgb.shape[:2]
    given = {"albedo": albedo, "normal": normal}
    guides = {name: _hwc(g, name, shape) for name, g in given.items() if g is not None}
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise OIDNError(f"OIDN threads must be a positive integer, got {threads!r}")
    if prefilter is not None:
        if prefilter not in QUALITIES:
            raise OIDNError(f"OIDN prefilter quality {prefilter!r}: expected one of {', '.join(QUALITIES)}")
        if guides:
            guides = {name: _run_guide(pyoidn, name, g, prefilter, threads) for name, g in guides.items()}
            clean_aux = True
    try:
        if threads is None:
            out = pyoidn.denoise(rgb, **guides, hdr=bool(hdr), clean_aux=bool(clean_aux), quality=quality)
        else:
            out = np.empty_like(rgb)
            with _PINNED_LOCK:
                _pinned(pyoidn, threads).run(pyoidn, {"color": rgb, **guides, "output": out}, bool(hdr),
                                             bool(clean_aux), quality)
    except (RuntimeError, ValueError, TypeError) as e:
        msg = " ".join(str(e).split())  # one line, whatever the library sent
        raise OIDNError(f"OIDN {version()} failed: {msg}") from e
    return np.ascontiguousarray(np.moveaxis(out, -1, 0))
