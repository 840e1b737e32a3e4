"""Shared test fixtures.

Devices are listed only when the hardware exists (STYLE.md item 11, as Mitsuba 3's conftest does):
a CPU-only machine runs the CPU cases and reports no skipped CUDA cases that would read as passes.
"""

from __future__ import annotations

import pytest
import torch

#: Devices to parametrise op and model tests over, in order of preference for fallback.
DEVICES: list[str] = (["cuda"] if torch.cuda.is_available() else []) + ["cpu"]

#: tests/test_cuda.py holds checks that need a GPU: not collected at all without one, so a
#: CPU-only run reports no skipped cases for them (`scripts/gpu_check.sh` runs them on a GPU).
collect_ignore = [] if torch.cuda.is_available() else ["test_cuda.py"]


@pytest.fixture(scope="module")
def mi():
    """The Mitsuba module in its LLVM variant; skips the test where the backend is unavailable."""
    from mcdenoise.errors import SceneError
    from mcdenoise.render._mitsuba import mitsuba

    try:
        return mitsuba()
    except SceneError as e:  # pragma: no cover - depends on the machine
        pytest.skip(f"Mitsuba LLVM backend unavailable: {e}")
