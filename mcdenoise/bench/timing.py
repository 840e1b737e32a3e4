"""Wall-clock timing: one median helper, and interleaved rounds over several methods.

Used by ``mcdenoise bench`` and the scripts in ``benchmarks/`` (one copy: ``benchmarks/_timing.py``
re-exports :func:`median_time`).
"""

from __future__ import annotations

import os
import statistics
import time
from typing import Any, Callable, Mapping

__all__ = ["median_time", "interleaved_times", "synchronizer", "usable_cores", "busy_warning"]


def usable_cores() -> int:
    """The cores this process may run on (its affinity mask; else every core)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def busy_warning(when: str = "", load: float | None = None) -> str | None:
    """A one-line warning when the 1-minute load average exceeds the usable cores: other work
    then shares the CPU and every time measured is slower and noisier than on a quiet machine.
    None when the machine is not overloaded or reports no load average. ``load`` overrides the
    measured figure (tests, or a figure recorded earlier)."""
    if load is None:
        if not hasattr(os, "getloadavg"):
            return None
        load = os.getloadavg()[0]
    cores = usable_cores()
    if load <= cores:
        return None
    return (f"load average {load:.2f}{' ' + when if when else ''} exceeds the {cores} usable core(s): other work "
            "shares the CPU, so these times are slower and noisier than on a quiet machine")


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
    groups: Mapping[str, str] | None = None,
) -> dict[str, list[float]]:
    """Time every function once per round, round-robin: ``{name: [seconds per round]}``.

    Interleaving puts a burst of background load on every method alike instead of on whichever
    method happened to run during it (the shared 2-core machine). ``sync`` runs before the clock
    starts and before it stops, so queued GPU work is counted in the call that queued it.
    Warm-up is the caller's (an untimed round). ``max_rounds`` caps the rounds of some
    functions (slow ones): they take part in the first rounds only, still interleaved.
    ``groups`` names each function's library (``"oidn"``, ``"torch"``): the first call after a
    call of another group is made once untimed before the timed one. Measured (issue 18): the
    first torch call after an OIDN call took 1.8x its steady time, even 2 s later, so whichever
    model came right after OIDN in the round order paid it (wskp 152 ms in one run, 467 in the
    next, with the API call beside it steady).
    """
    out: dict[str, list[float]] = {name: [] for name in fns}
    last: str | None = None
    for r in range(rounds):
        for name, fn in fns.items():
            if max_rounds is not None and r >= max_rounds.get(name, rounds):
                continue
            group = groups.get(name) if groups is not None else None
            if group is not None and last is not None and group != last:
                fn()  # untimed: settle after the other library's call
            last = group
            sync()
            t0 = time.perf_counter()
            fn()
            sync()
            out[name].append(time.perf_counter() - t0)
        if on_round is not None:
            on_round(r)
    return out
