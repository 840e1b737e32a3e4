"""Lazy Mitsuba 3 import with a working LLVM backend.

Mitsuba and Dr.Jit are imported only when a render is asked for: JIT start-up costs seconds and
``import mcdenoise`` must stay cheap. The LLVM backend needs ``libLLVM`` at run time; on Debian the
library is not on Dr.Jit's default search path, so we point ``DRJIT_LIBLLVM_PATH`` at it before
the first import.
"""

from __future__ import annotations

import glob
import os
from types import ModuleType

from mcdenoise.errors import SceneError

__all__ = ["mitsuba", "find_libllvm", "VARIANT"]

VARIANT = "llvm_ad_rgb"

_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so*",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19*",
    "/usr/lib/llvm-19/lib/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM.so.19*",
)

_MI: ModuleType | None = None


def find_libllvm() -> str | None:
    """Path of Debian's libLLVM 19, or None when none is installed."""
    for pattern in _LLVM_GLOBS:
        hits = sorted(p for p in glob.glob(pattern) if os.path.isfile(p))
        if hits:
            return hits[0]
    return None


def mitsuba() -> ModuleType:
    """The ``mitsuba`` module with variant ``llvm_ad_rgb`` set; raises SceneError when impossible."""
    global _MI
    if _MI is not None:
        # The variant is process-global: user code (or a test) may have switched it since.
        if _MI.variant() != VARIANT:
            _MI.set_variant(VARIANT)
        return _MI
    if not os.environ.get("DRJIT_LIBLLVM_PATH"):
        lib = find_libllvm()
        if lib is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    try:
        import mitsuba as mi
    except ImportError as e:
        raise SceneError(f"cannot import mitsuba ({e}); install it with `pip install mitsuba`") from None
    try:
        mi.set_variant(VARIANT)
    except Exception as e:  # noqa: BLE001 - mitsuba raises plain ImportError/RuntimeError here
        raise SceneError(
            f"cannot enable Mitsuba variant {VARIANT!r} ({e}); the LLVM backend needs libLLVM: set "
            f"DRJIT_LIBLLVM_PATH to libLLVM.so (Debian: apt-get install libllvm19)"
        ) from None
    # Registering here (not at import) keeps the integrator available to XML scenes and mi.render.
    from mcdenoise.render import integrator as _integrator

    _integrator.register()
    _MI = mi
    return mi
