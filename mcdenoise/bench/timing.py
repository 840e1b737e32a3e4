"""Wall-clock timing: one median helper, and interleaved rounds over several methods.

Used by ``mcdenoise bench`` and the scripts in ``benchmarks/`` (one copy: ``benchmarks/_timing.py``
re-exports :func:`median_time`).
"""

from __future__ import annotations

import statistics
import time
from typing import Any, Callable, Mapping

__all__ = ["median_time", "interleaved_times", "synchronizer"]


def median_time(fn: Callable[[], Any], repeats: int, warmup: int = 0) -> float:
    """Median wall time in seconds of ``repeats`` calls of ``fn`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def synchronizer(device: str) -> Callable[[], None]:
    """A function that waits for queued GPU work on ``device`` (a no-op on the CPU)."""
    if device.startswith("cuda"):
        import torch

        return torch.cuda.synchronize
    return lambda: None


def interleaved_times(
    fns: Mapping[str, Callable[[], Any]],
    rounds: int,
    *,
    sync: Callable[[], None] = lambda: None,
    on_round: Callable[[int], None] | None = None,
    max_rounds: Mapping[str, int] | None = None,
) -> dict[str, list[float]]:
    """Time every function once per round, round-robin: ``{name: [seconds per round]}``.

    Interleaving puts a burst of background load on every method alike instead of on whichever
    method happened to run during it (the shared 2-core machine). ``sync`` runs before the clock
    starts and before it stops, so queued GPU work is counted in the call that queued it.
    Warm-up is the caller's (an untimed round). ``max_rounds`` caps the rounds of some
    functions (slow ones): they take part in the first rounds only, still interleaved.
    """
    out: dict[str, list[float]] = {name: [] for name in fns}
    for r in range(rounds):
        for name, fn in fns.items():
            if max_rounds is not None and r >= max_rounds.get(name, rounds):
                continue
            sync()
            t0 = time.perf_counter()
            fn()
            sync()
            out[name].append(time.perf_counter() - t0)
        if on_round is not None:
            on_round(r)
    return out
