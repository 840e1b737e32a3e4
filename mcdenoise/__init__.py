"""mcdenoise: neural denoising of Monte Carlo renderings.

Pipeline, one sub-package per stage: render -> data -> ops -> models -> train -> eval -> cli.

``mcdenoise.denoise(color, albedo, normal, depth, ...)`` denoises arrays (see docs/DENOISE.md); it
is imported on first use, so ``import mcdenoise`` stays light.
"""

from __future__ import annotations

import os as _os
from typing import Any

# Large tensors on 2 MiB pages (PyTorch's CPU allocator, read once at its first large allocation,
# so it must be set before torch allocates). Our per-sample tensors are hundreds of MB and fresh
# each call, and on 4 KiB pages their first write is page-fault bound (figures per model:
# benchmarks/bench_fast_paths.py --parts thp, in docs/PERFORMANCE.md). THP_MEM_ALLOC_ENABLE=0 in
# the environment turns it off.
_os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

__version__ = "0.1.0"
__all__ = ["__version__", "denoise"]


def __getattr__(name: str) -> Any:
    # Lazy: the API pulls in torch and the models; the CLI's --version must not.
    if name == "denoise":
        from mcdenoise.infer.api import denoise

        return denoise
    raise AttributeError(f"module 'mcdenoise' has no attribute {name!r}")
