"""Peak memory of one call, per call, in the running process.

CPU: the Linux peak resident set size (``VmHWM``) is reset before the call by writing ``5`` to
``/proc/self/clear_refs``, after ``gc.collect()`` and glibc's ``malloc_trim(0)`` have handed freed
heap pages back to the kernel; the figure is ``VmHWM`` after the call minus ``VmRSS`` before it:
every page the call touched beyond what was already resident (inputs and weights are resident
before, so they are not counted). This sees what ``tracemalloc`` cannot (torch and OIDN allocate
outside Python's allocator) and, unlike ``ru_maxrss``, is per call rather than per process.
Without a writable ``clear_refs`` (non-Linux, some sandboxes) it returns None.

CUDA: ``torch.cuda.max_memory_allocated`` after ``reset_peak_memory_stats``, minus the allocated
bytes before (torch's caching allocator; memory held by other libraries is not seen).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import functools
from typing import Any, Callable

__all__ = ["peak_call_memory", "cpu_peak_supported", "MEMORY_METHOD"]

#: How the CPU figure is taken, for reports.
MEMORY_METHOD = ("peak RSS of the call above the RSS before it (Linux VmHWM reset through "
                 "/proc/self/clear_refs after gc and malloc_trim)")


@functools.lru_cache(maxsize=1)
def _libc() -> Any:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name) if name else None
    except OSError:
        return None


def status_kib(field: str) -> int:
    """A ``/proc/self/status`` field in KiB (``VmRSS``, ``VmHWM``); OSError where there is none."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise OSError(f"/proc/self/status has no {field}")


def _reset_cpu_peak() -> bool:
    gc.collect()
    libc = _libc()
    if libc is not None and hasattr(libc, "malloc_trim"):
        libc.malloc_trim(0)
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return False
    return True


@functools.lru_cache(maxsize=1)
def cpu_peak_supported() -> bool:
    """True when the per-call CPU peak can be measured here."""
    try:
        status_kib("VmHWM")
    except OSError:
        return False
    return _reset_cpu_peak()


def peak_call_memory(fn: Callable[[], Any], device: str = "cpu") -> tuple[Any, int | None]:
    """Run ``fn()`` once; return ``(its result, peak bytes it needed above the memory in use before)``.

    The byte count is None where it cannot be measured (see the module docstring).
    """
    if device.startswith("cuda"):
        import torch

        torch.cuda.synchronize()
        before = torch.cuda.memory_allocated()
        torch.cuda.reset_peak_memory_stats()
        out = fn()
        torch.cuda.synchronize()
        return out, int(torch.cuda.max_memory_allocated() - before)
    if not cpu_peak_supported() or not _reset_cpu_peak():
        return fn(), None
    before = status_kib("VmRSS")
    out = fn()
    peak = status_kib("VmHWM")
    return out, max(0, peak - before) * 1024
