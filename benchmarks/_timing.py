"""Timing helper shared by the benchmark scripts (run as ``python benchmarks/bench_*.py``, so this
folder is on ``sys.path``). The one copy lives in :mod:`mcdenoise.bench.timing`."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mcdenoise.bench.timing import median_time  # noqa: E402

__all__ = ["median_time"]
