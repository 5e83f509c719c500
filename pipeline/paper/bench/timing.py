"""Timing of one accuracy-bench measurement: build once, run best of N, score once."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

from pipeline.paper.bench.pareto import Row


@dataclasses.dataclass(frozen=True)
class PendingRun:
    """A setting to time (``run``) and how to turn its time and result into row(s)."""

    run: Callable[[], object]
    finish: Callable[[float, object], Row | list[Row]]


def time_runs(pending: Sequence[PendingRun], repeats: int) -> list[Row]:
    rows: list[Row] = []
    for p, (seconds, result) in zip(pending, best_times([p.run for p in pending], repeats)):
        done = p.finish(seconds, result)
        rows += done if isinstance(done, list) else [done]
    return rows



def best_times(fns: Sequence[Callable[[], object]], repeats: int) -> list[tuple[float, object]]:
    """Best wall time (s) of ``repeats`` runs of each callable, and its last result.

    The callables are run round-robin (all once, then all again, ...), so a change in
    machine load during a sweep hits every setting alike. A call under 50 ms is
    looped within each sample so clock resolution and scheduling jitter stay small
    against it.
    """
    best, results, inner = [], [], []
    for fn in fns:
        start = time.perf_counter()
        results.append(fn())
        first = time.perf_counter() - start
        inner.append(min(20, max(1, math.ceil(0.05 / max(first, 1e-6)))))
        best.append(first)
    for _ in range(max(repeats - 1, 1)):
        for i, fn in enumerate(fns):
            start = time.perf_counter()
            for _ in range(inner[i]):
                results[i] = fn()
            best[i] = min(best[i], (time.perf_counter() - start) / inner[i])
    return list(zip(best, results))
