"""Lazy Mitsuba 3 import with a working backend: LLVM on the CPU, CUDA where a GPU is present.

Mitsuba and Dr.Jit are imported only when a render is asked for: JIT start-up costs seconds and
``import mcdenoise`` must stay cheap. The LLVM backend needs ``libLLVM`` at run time; on Debian the
library is not on Dr.Jit's default search path, so we point ``DRJIT_LIBLLVM_PATH`` at it before
the first import.

Variant choice (once per process, at the first render): ``set_variant(name)`` (the CLI's
``--variant``), else the environment variable ``MCDENOISE_VARIANT``, else ``auto``: Mitsuba's
``cuda_ad_rgb`` when the CUDA driver reports a device and the installed Mitsuba has that variant,
``llvm_ad_rgb`` otherwise. The variant is process-global in Mitsuba and our integrator class is
built for one variant, so it cannot change after the first render.
"""

from __future__ import annotations

import ctypes
import glob
import os
from types import ModuleType

from mcdenoise.errors import SceneError

__all__ = [
    "mitsuba",
    "find_libllvm",
    "VARIANT",
    "CPU_VARIANT",
    "GPU_VARIANT",
    "VARIANTS",
    "cuda_available",
    "select_variant",
    "set_variant",
    "active_variant",
    "process_variant",
    "variant_of_renderer",
]

CPU_VARIANT = "llvm_ad_rgb"
GPU_VARIANT = "cuda_ad_rgb"
#: Variants the renderer supports (it needs a JIT backend: no scalar variants), plus "auto".
VARIANTS = ("auto", CPU_VARIANT, GPU_VARIANT)
#: The variant in use once a render started (the CPU variant until then).
VARIANT = CPU_VARIANT

_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so*",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19*",
    "/usr/lib/llvm-19/lib/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19*",
)

_MI: ModuleType | None = None
_REQUESTED: str | None = None


def find_libllvm() -> str | None:
    """Path of Debian's libLLVM 19, or None when none is installed."""
    for pattern in _LLVM_GLOBS:
        hits = sorted(p for p in glob.glob(pattern) if os.path.isfile(p))
        if hits:
            return hits[0]
    return None


def cuda_available() -> bool:
    """True when the CUDA driver (``libcuda``) loads and reports at least one device.

    Asks the driver directly through ctypes, so neither torch nor Dr.Jit's CUDA backend is
    initialised just to find out.
    """
    for name in ("libcuda.so.1", "libcuda.so"):
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        count = ctypes.c_int(0)
        try:
            if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0:
                return False
        except AttributeError:
            return False
        return count.value > 0
    return False


def _built_variants() -> list[str]:
    """Variants the installed Mitsuba was built with ([] when Mitsuba is missing)."""
    try:
        import mitsuba as mi
    except ImportError:
        return []
    return list(mi.variants())


def select_variant(requested: str | None = None) -> str:
    """The Mitsuba variant to use: ``requested`` unless None or ``"auto"``, else the environment
    variable ``MCDENOISE_VARIANT``, else the GPU variant when :func:`cuda_available` and Mitsuba
    has it, else the CPU variant. Raises SceneError for a variant we do not support."""
    name = requested if requested not in (None, "auto") else os.environ.get("MCDENOISE_VARIANT", "auto") or "auto"
    if name not in VARIANTS:
        raise SceneError(f"Mitsuba variant {name!r} is not supported; choose one of {', '.join(VARIANTS)}")
    if name != "auto":
        return name
    if cuda_available() and GPU_VARIANT in _built_variants():
        return GPU_VARIANT
    return CPU_VARIANT


def set_variant(name: str | None) -> str:
    """Fix the variant of this process (``None``/``"auto"`` choose as :func:`select_variant`).

    Call it before the first render; afterwards only the variant already in use is accepted.
    Returns the variant chosen.
    """
    global _REQUESTED
    chosen = select_variant(name)
    if _MI is not None and chosen != VARIANT:
        raise SceneError(f"Mitsuba variant {VARIANT!r} is already in use in this process; cannot switch to {chosen!r}")
    _REQUESTED = chosen
    return chosen


def active_variant() -> str | None:
    """The variant in use, or None before the first render."""
    return VARIANT if _MI is not None else None


def process_variant() -> str:
    """The variant this process renders (or will render) with: the one in use, else the one
    :func:`set_variant` fixed, else :func:`select_variant`'s choice. Imports nothing heavy."""
    if _MI is not None:
        return VARIANT
    return _REQUESTED or select_variant(None)


def variant_of_renderer(renderer: str) -> str | None:
    """The variant named in an image's ``renderer`` string (``"mitsuba 3.9.1 (llvm_ad_rgb) / ..."``,
    written by ``mcdenoise.render.image._renderer_string``), or None when it names none."""
    import re

    m = re.search(r"\(([a-z0-9_]+)\)", renderer or "")
    return m.group(1) if m else None


def mitsuba() -> ModuleType:
    """The ``mitsuba`` module with this process's variant set; raises SceneError when impossible."""
    global _MI, VARIANT
    if _MI is not None:
        # The variant is process-global: user code (or a test) may have switched it since.
        if _MI.variant() != VARIANT:
            _MI.set_variant(VARIANT)
        return _MI
    variant = _REQUESTED or select_variant(None)
    if variant == CPU_VARIANT and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        lib = find_libllvm()
        if lib is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    try:
        import mitsuba as mi
    except ImportError as e:
        raise SceneError(f"cannot import mitsuba ({e}); install it with `pip install mitsuba`") from None
    try:
        mi.set_variant(variant)
    except Exception as e:  # noqa: BLE001 - mitsuba raises plain ImportError/RuntimeError here
        hint = ("the LLVM backend needs libLLVM: set DRJIT_LIBLLVM_PATH to libLLVM.so (Debian: apt-get install "
                "libllvm19)") if variant == CPU_VARIANT else "the CUDA backend needs an NVIDIA GPU and its driver"
        raise SceneError(f"cannot enable Mitsuba variant {variant!r} ({e}); {hint}") from None
    VARIANT = variant
    # Registering here (not at import) keeps the integrator available to XML scenes and mi.render.
    from mcdenoise.render import integrator as _integrator

    _integrator.register()
    _MI = mi
    return mi
