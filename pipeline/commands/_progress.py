"""Progress bars for long jobs (rich), silent with ``--quiet`` or when not on a terminal."""

from __future__ import annotations

import contextlib
import sys


@contextlib.contextmanager
def stage_progress(*, enabled: bool = True):
    """Yield ``update(stage, done, total)``: one bar per stage (read/align, accumulate, ...)."""
    if not enabled or not sys.stderr.isatty():
        yield lambda stage, done, total: None
        return
    # rich is imported only for a terminal (20 ms of start-up, issue 15)
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bars = Progress(
        TextColumn("{task.description:<12}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        transient=False,
    )
    tasks: dict[str, int] = {}

    def update(stage: str, done: int, total: int) -> None:
        if stage not in tasks:
            tasks[stage] = bars.add_task(stage, total=total)
        bars.update(tasks[stage], completed=done, total=total)

    with bars:
        yield update
