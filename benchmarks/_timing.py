"""Timing shared by the benchmarks (run as scripts, so this directory is on ``sys.path``)."""

from __future__ import annotations

import statistics
import time


def median_time(fn, repeats: int = 7) -> float:
    """Median wall time (s) of ``repeats`` calls of ``fn()``."""
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)
