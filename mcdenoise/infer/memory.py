"""Peak memory of one model call, measured, and the tile size that fits a memory budget.

The cost of running a model on a window of ``P`` pixels is modelled as ``a + b * P`` bytes and
``a``, ``b`` are *measured* on two small probe windows with the caller's sample count:

* on CUDA, by the caching allocator's peak (``torch.cuda.max_memory_allocated``);
* on the CPU, by :class:`PeakTracker`, which follows every tensor storage the forward creates and
  sums those still alive after each operator (PyTorch's CPU allocator keeps no statistics).

Both probes include the input tensors of the window. Some models bound their own working set on
large inputs (SBMC's and the layer model's row bands), so their true cost grows slower than the
line fitted on small probes: the fit over-estimates there, which only makes tiles smaller.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import torch
import torch.utils._pytree as pytree
from torch.multiprocessing.reductions import StorageWeakRef
from torch.utils._python_dispatch import TorchDispatchMode

from mcdenoise.models.registry import Denoiser, synthetic_batch

__all__ = ["PeakTracker", "MemoryCost", "measure_cost", "parse_memory", "DEFAULT_MAX_MEMORY"]

#: Budget when the user gives none: fits an 8 GB machine with room for the rest of the process.
DEFAULT_MAX_MEMORY = 4 << 30
_UNITS = {"": 1, "B": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def parse_memory(text: str | int | float) -> int:
    """``"4G"``, ``"512M"``, ``"1.5GB"``, ``"123456"`` (bytes) -> bytes (binary units)."""
    if isinstance(text, (int, float)):
        if text <= 0:
            raise ValueError(f"memory budget must be positive, got {text}")
        return int(text)
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([KMGT]?)(?:i?B)?\s*", str(text), re.IGNORECASE)
    if m is None or float(m.group(1)) <= 0:
        raise ValueError(f"cannot read memory budget {text!r}; write e.g. 4G, 512M or 2.5GB")
    return int(float(m.group(1)) * _UNITS[m.group(2).upper()])


class PeakTracker(TorchDispatchMode):
    """Peak bytes of tensor storages alive during a block (CPU or any device), under dispatch.

    Counts storages that operators return (views share their base's storage and count once);
    scratch memory an operator frees before returning is not seen. ``extra`` adds bytes that are
    alive throughout (the inputs).
    """

    @classmethod
    def _should_skip_dynamo(cls) -> bool:
        # PyTorch wraps a mode's __torch_dispatch__ in "dynamo disabled", which imports
        # torch._dynamo on the first operator (tens of seconds on a loaded 2-core machine). This
        # mode never runs under torch.compile, so the wrapper buys nothing.
        return False

    def __init__(self, extra: int = 0) -> None:
        super().__init__()
        self._live: dict[int, tuple[StorageWeakRef, int]] = {}
        self.extra = extra
        self.peak = extra

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        out = func(*args, **(kwargs or {}))
        for t in pytree.tree_leaves(out):
            if isinstance(t, torch.Tensor) and t.device.type != "meta":
                st = t.untyped_storage()
                key = st.data_ptr()
                old = self._live.get(key)
                if old is None or old[0].expired():
                    self._live[key] = (StorageWeakRef(st), st.nbytes())
        dead = [k for k, (ref, _) in self._live.items() if ref.expired()]
        for k in dead:
            del self._live[k]
        self.peak = max(self.peak, self.extra + sum(n for _, n in self._live.values()))
        return out


@dataclass(frozen=True)
class MemoryCost:
    """Peak bytes of one model call on a window of ``pixels`` pixels: ``fixed + per_pixel * pixels``."""

    fixed: float
    per_pixel: float

    def bytes(self, pixels: int) -> float:
        return self.fixed + self.per_pixel * pixels

    def max_pixels(self, budget: float) -> int:
        """Largest window (pixels) whose call fits ``budget`` bytes (0 when even the fixed part does not)."""
        room = budget - self.fixed
        return max(0, int(room // self.per_pixel)) if self.per_pixel > 0 else (1 << 62)


def _batch_bytes(batch: dict[str, torch.Tensor]) -> int:
    return sum(v.numel() * v.element_size() for v in batch.values())


def _peak(model: Denoiser, batch: dict[str, torch.Tensor], device: torch.device) -> int:
    with torch.no_grad():
        if device.type == "cuda":
            torch.cuda.synchronize(device)
            torch.cuda.reset_peak_memory_stats(device)
            base = torch.cuda.memory_allocated(device)
            model(batch)
            torch.cuda.synchronize(device)
            # The inputs were allocated before the reset: the allocator's peak includes them.
            return torch.cuda.max_memory_allocated(device) - base + _batch_bytes(batch)
        tracker = PeakTracker(extra=_batch_bytes(batch))
        with tracker:
            model(batch)
        return tracker.peak


def measure_cost(model: Denoiser, spp: int, device: torch.device | str = "cpu", *, align: int = 1) -> MemoryCost:
    """Fit ``fixed + per_pixel * pixels`` to the peak of two probe windows (32^2 and 64^2, aligned up)."""
    device = torch.device(device)
    sizes = [math.ceil(s / align) * align for s in (32, 64)]
    peaks = []
    g = torch.Generator().manual_seed(0)
    for s in sizes:
        batch = synthetic_batch(model, spp=max(1, spp), height=s, width=s, generator=g)
        batch = {k: v.to(device) for k, v in batch.items()}
        peaks.append(_peak(model, batch, device))
        del batch
    p0, p1 = sizes[0] ** 2, sizes[1] ** 2
    per_pixel = max(0.0, (peaks[1] - peaks[0]) / (p1 - p0))
    fixed = max(0.0, peaks[1] - per_pixel * p1)
    return MemoryCost(fixed, per_pixel)
