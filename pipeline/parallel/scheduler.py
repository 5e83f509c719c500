"""Where dask graphs run (local threads or a ``dask.distributed`` cluster) and
per-task progress on local schedulers.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import dask
from dask.callbacks import Callback

from pipeline.core import validate
from pipeline.errors import InputError


class _TaskProgress(Callback):
    """Counts finished tasks whose key starts with ``prefix`` (local schedulers only)."""

    def __init__(self, prefix: str, report: Callable[[int], None]) -> None:
        super().__init__()
        self.prefix, self.report, self.done = prefix, report, 0

    def _posttask(self, key, result, dsk, state, worker_id) -> None:
        name = key[0] if isinstance(key, tuple) else key
        if str(name).startswith(self.prefix):
            self.done += 1
            self.report(self.done)


# ----------------------------------------------------------------------------- scheduler
@contextlib.contextmanager
def scheduler_context(scheduler: str | None = None, threads: int | None = None):
    """Local threads (default) or a dask.distributed cluster at ``scheduler`` (tcp://...)."""
    if threads is not None:
        validate.whole("--threads", threads)
    if scheduler:
        from distributed import Client

        try:
            client = Client(scheduler, timeout="10s", set_as_default=False)
        except OSError as err:
            raise InputError(f"--scheduler {scheduler}: cannot connect ({err})") from err
        with client, dask.config.set(scheduler=client):
            yield
    else:
        with dask.config.set(scheduler="threads", num_workers=threads):
            yield
