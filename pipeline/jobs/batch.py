"""Many stacks as one dask graph, on the local machine or a dask.distributed cluster.

The graph has one task per stack (:func:`run_stack_task`), which runs the whole
single-stack job (:func:`pipeline.jobs.stack.process_stack`) on a *local* threaded
scheduler inside the task. Why one task per stack rather than one big graph
of every stack's frame-level tasks (or ``secede``/``rejoin`` into the cluster):

* **Locality**: a stack's frames are read, warped and summed in the process that
  reads them; full-resolution frames never cross the network.
* **Bounded memory**: at most ``concurrency`` stacks are in flight (local: the
  threaded scheduler's workers; cluster: a sliding window of submitted tasks,
  and one stack per worker thread), each with the engine's own bounded
  footprint (a binary tree of merges holds a few frames at a time).
* **Identical results**: the same code runs the same per-stack graph on the same
  kind of scheduler whether the batch runs locally or on a cluster.
* **Fault tolerance**: a task is idempotent (it only writes its own output,
  atomically), so when a worker dies the distributed scheduler simply runs it
  again elsewhere.

On a distributed worker a nested ``dask.compute`` would, by default, find the
worker's client and submit the stack's small tasks to the cluster while
blocking a worker thread; :func:`_local_scheduler` pins nested computes to
local threads instead. ``dask.config`` is process-global, so the setting is
reference-counted across the tasks running concurrently in one worker process.

Progress: ``on_progress(key, stage, done, total)`` per stack (forwarded from
cluster workers as ``flexdof-progress`` events) and ``on_result(result)`` once
per finished stack, in the calling thread.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import socket
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import dask
from dask.callbacks import Callback

from pipeline.core import validate
from pipeline.errors import FlexdofError, InputError
from pipeline.io.hashing import sha256_file
from pipeline.io.write import OutputError
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.scheduler import (
    CONNECT_TIMEOUT,
    SchedulerError,
    check_scheduler,
    local_threads,
)

log = logging.getLogger(__name__)

PROGRESS_TOPIC = "flexdof-progress"

OnResult = Callable[[dict], None]
OnProgress = Callable[[str, str, int, int], None]


@dataclasses.dataclass(frozen=True)
class BatchJob:
    """One stack of a batch: its inputs (as :func:`pipeline.io.stackfile.load_stack` takes them),
    its output image and options. ``key`` names it in results and progress."""

    key: str
    paths: tuple[str, ...]
    output: str
    options: StackOptions = dataclasses.field(default_factory=StackOptions)


# ---------------------------------------------------------------------- the task
_pin_lock = threading.Lock()
_pin_users = 0
_pin_config: object | None = None
_pin_cv_threads = 1
_local_sinks: dict[str, OnProgress] = {}


class _LocalScheduler:
    """Pin nested ``dask.compute`` calls in this process to ``threads`` local threads,
    and OpenCV's own thread pool to as many (stacks, not pixels, are the batch's
    parallelism; it also keeps OpenCV's multi-threaded reductions in one order).

    Reference-counted: the first task in a process sets the config, the last
    one out restores it, so concurrent tasks never see it flip under them.
    """

    def __init__(self, threads: int) -> None:
        self.threads = threads

    def __enter__(self) -> None:
        global _pin_users, _pin_config, _pin_cv_threads
        with _pin_lock:
            if _pin_users == 0:
                _pin_config = dask.config.set(scheduler="threads", num_workers=self.threads)
                _pin_cv_threads = cv2.getNumThreads()
                cv2.setNumThreads(self.threads)
            _pin_users += 1

    def __exit__(self, *exc) -> None:
        global _pin_users, _pin_config
        with _pin_lock:
            _pin_users -= 1
            if _pin_users == 0 and _pin_config is not None:
                _pin_config.__exit__(None, None, None)
                _pin_config = None
                cv2.setNumThreads(_pin_cv_threads)


def _progress_sink(key: str, run_token: str) -> Callable[[str, int, int], None]:
    """Where a task reports its stages: the cluster's event log, or the local driver."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        worker = None
    if worker is not None:

        def report(stage: str, done: int, total: int) -> None:
            worker.log_event(
                PROGRESS_TOPIC,
                {"key": key, "stage": stage, "done": done, "total": total, "run": run_token},
            )

        return report
    sink = _local_sinks.get(run_token)
    if sink is None:
        return lambda stage, done, total: None
    return lambda stage, done, total: sink(key, stage, done, total)


def run_stack_task(job: BatchJob, threads: int, run_token: str = "") -> dict:
    """Process one stack; return a small, picklable summary (never the image).

    A failing stack fails alone: its error is returned as data (``status`` =
    ``"failed"``; ``error_kind`` ``"input"`` for errors in the input that a
    retry cannot fix (an :class:`InputError`), else ``"error"``: a full disk or
    another transient write failure, a lost worker, a ValueError or other failure
    inside numpy/scipy; workflows retry those on the next run) so the rest of the
    batch goes on.
    """
    started = time.time()
    result = {
        "key": job.key,
        "output": job.output,
        "started": started,
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }
    progress = _progress_sink(job.key, run_token)
    try:
        with _LocalScheduler(threads):
            stack_result = process_stack(
                list(job.paths), job.output, job.options, progress=progress
            )
        result.update(
            status="done",
            timings=stack_result.sidecar.get("timings_s"),
            output_sha256=sha256_file(Path(job.output)),
        )
    except OutputError as err:  # disk full: retried next run; a bad name or folder: not
        kind = "error" if err.transient else "input"
        result.update(status="failed", error_kind=kind, error=_describe(err))
    except InputError as err:
        result.update(status="failed", error_kind="input", error=_describe(err))
    except (FlexdofError, OSError, ValueError, MemoryError) as err:  # transient or a bug
        result.update(status="failed", error_kind="error", error=_describe(err))
    except Exception as err:  # isolate one stack's bug from the batch; reported, not hidden
        log.error("stack %s: unexpected error\n%s", job.key, traceback.format_exc())
        result.update(
            status="failed",
            error_kind="error",
            error=f"internal error: {type(err).__name__}: {err}",
        )
    result["finished"] = time.time()
    result["seconds"] = result["finished"] - started
    return result


def _describe(err: BaseException) -> str:
    text = str(err) or type(err).__name__
    return text if isinstance(err, FlexdofError) else f"{type(err).__name__}: {text}"


def batch_graph(jobs: Sequence[BatchJob], *, threads_per_stack: int = 1, run_token: str = ""):
    """The batch as dask Delayed objects: one :func:`run_stack_task` per job."""
    return [
        dask.delayed(run_stack_task, pure=False)(
            job, threads_per_stack, run_token, dask_key_name=f"flexdof-stack-{i}-{_token(job)}"
        )
        for i, job in enumerate(jobs)
    ]


def _token(job: BatchJob) -> str:
    return hashlib.sha1(repr(job).encode("utf-8")).hexdigest()[:12]


# ---------------------------------------------------------------------- drivers
def run_batch(
    jobs: Sequence[BatchJob],
    *,
    scheduler: str | None = None,
    concurrency: int | None = None,
    threads_per_stack: int | None = None,
    on_result: OnResult | None = None,
    on_progress: OnProgress | None = None,
) -> list[dict]:
    """Process ``jobs``; return their results in job order.

    Parameters
    ----------
    jobs : sequence of BatchJob
    scheduler : str, optional
        A dask.distributed scheduler address (``tcp://host:port``); default:
        ``dask.config`` ``scheduler-address`` (env ``DASK_SCHEDULER_ADDRESS``)
        if set, else the local machine.
    concurrency : int, optional
        Stacks in flight at once (bounds memory). Default: local, the number of
        cores; cluster, its total worker threads.
    threads_per_stack : int, optional
        Local threads of each stack's own graph. Default: local,
        ``cores // concurrency`` (at least 1); cluster, 1 (one stack per worker
        thread already fills the cluster).
    on_result, on_progress : callable, optional
        Called in this thread for every finished stack, and for each stack's
        progress stages.
    """
    if concurrency is not None:
        validate.whole("concurrency", concurrency)
    if threads_per_stack is not None:
        validate.whole("threads_per_stack", threads_per_stack)
    address = scheduler or dask.config.get("scheduler-address", None)
    if not jobs:
        return []
    if address:
        return _run_distributed(
            jobs, address, concurrency, threads_per_stack or 1, on_result, on_progress
        )
    cores = os.cpu_count() or 1
    concurrency = min(concurrency or cores, len(jobs))
    threads = threads_per_stack or max(1, cores // concurrency)
    return _run_local(jobs, concurrency, threads, on_result, on_progress)


class _ResultCallback(Callback):
    """Hand each finished stack to ``on_result`` as soon as the local scheduler has it."""

    def __init__(self, on_result: OnResult) -> None:
        super().__init__()
        self.on_result = on_result

    def _posttask(self, key, result, dsk, state, worker_id) -> None:
        self.on_result(result)


def _run_local(jobs, concurrency, threads, on_result, on_progress) -> list[dict]:
    token = f"local-{os.getpid()}-{time.monotonic_ns()}"
    graph = batch_graph(jobs, threads_per_stack=threads, run_token=token)
    if on_progress is not None:
        _local_sinks[token] = on_progress
    try:
        with _ResultCallback(on_result or (lambda result: None)):
            results = dask.compute(*graph, scheduler=local_threads(concurrency))
    finally:
        _local_sinks.pop(token, None)
    return list(results)


def _run_distributed(jobs, address, concurrency, threads, on_result, on_progress) -> list[dict]:
    from distributed import Client, as_completed

    check_scheduler(address)  # a one-line error within seconds if no scheduler answers
    try:
        client = Client(address, timeout=CONNECT_TIMEOUT, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise SchedulerError(f"scheduler {address}: cannot connect ({err})") from err
    token = f"dist-{socket.gethostname()}-{os.getpid()}-{time.monotonic_ns()}"
    graph = batch_graph(jobs, threads_per_stack=threads, run_token=token)
    order = {job.key: i for i, job in enumerate(jobs)}
    results: list[dict | None] = [None] * len(jobs)
    with client:
        if on_progress is not None:

            def forward(event) -> None:
                msg = event[1]
                if isinstance(msg, dict) and msg.get("run") == token:
                    on_progress(msg["key"], msg["stage"], msg["done"], msg["total"])

            client.subscribe_topic(PROGRESS_TOPIC, forward)
        window = concurrency or max(1, sum(client.nthreads().values()))
        pending = iter(zip(jobs, graph))
        futures = {}
        running = as_completed(loop=client.loop)

        def submit_next() -> None:
            nxt = next(pending, None)
            if nxt is not None:
                future = client.compute(nxt[1])
                futures[future] = nxt[0]
                running.add(future)

        for _ in range(window):
            submit_next()
        finished = 0
        try:
            for future in running:
                job = futures.pop(future)
                result = _future_result(future, job)
                results[order[job.key]] = result
                finished += 1
                if on_result is not None:
                    on_result(result)
                submit_next()
        except _LOST as err:
            raise SchedulerError(
                f"scheduler {address}: lost the connection mid-run ({finished} of {len(jobs)} "
                f"stacks finished; the others are retried by the next run): "
                f"{type(err).__name__}: {err}"
            ) from err
        finally:
            for future in futures:
                future.cancel()
            if on_progress is not None:
                client.unsubscribe_topic(PROGRESS_TOPIC)
    return [r for r in results if r is not None]


def _lost_errors() -> tuple[type[BaseException], ...]:
    from concurrent.futures import CancelledError

    return (OSError, TimeoutError, CancelledError)


_LOST = _lost_errors()  # what a vanished scheduler raises in the client (CommClosedError: OSError)


def _future_result(future, job: BatchJob) -> dict:
    """The task's result; a task the cluster gave up on (e.g. it killed its workers
    repeatedly) becomes a failed stack."""
    from distributed import KilledWorker

    try:
        return future.result()
    except KilledWorker as err:
        now = time.time()
        return {
            "key": job.key,
            "output": job.output,
            "status": "failed",
            "error_kind": "error",
            "error": f"the cluster gave up on this stack: {err}",
            "started": now,
            "finished": now,
            "seconds": 0.0,
            "worker": None,
        }
