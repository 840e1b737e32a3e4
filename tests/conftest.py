"""Shared test fixtures.

Devices are listed only when the hardware exists (STYLE.md item 11, as Mitsuba 3's conftest does):
a CPU-only machine runs the CPU cases and reports no skipped CUDA cases that would read as passes.
"""

from __future__ import annotations

import torch

#: Devices to parametrise op and model tests over, in order of preference for fallback.
DEVICES: list[str] = (["cuda"] if torch.cuda.is_available() else []) + ["cpu"]
