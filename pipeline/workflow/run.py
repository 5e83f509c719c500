"""Workflow files (``workflows/*.toml``): many stacks, incremental and scheduled runs.

A workflow names its inputs (globs of stack directories, or of frame files
grouped into stacks), the options of the main job (Sec. 9 / Sec. 4 pipeline:
lens, alignment, deconvolution method), where the outputs go and how they are
named, the concurrency and an optional schedule. The whole file is validated
(unknown keys, types, inputs that match nothing, output names that would leave
the output directory or collide) before any work starts.

A run (:func:`run_workflow`) processes only stacks whose *fingerprint* -- the
SHA-256 of every input file's content, the options, the output name and the
flexdof version -- differs from the ledger's last completed one, records every
stack in the ledger (:mod:`pipeline.workflow.ledger`) and holds the output directory's
run lock throughout. The commented examples in ``workflows/`` document the
schema.
"""

from __future__ import annotations

import dataclasses
import glob
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

from pipeline.errors import FlexdofError, InputError
from pipeline.io.write import temp_prefix
from pipeline.jobs.batch import BatchJob, OnProgress, run_batch
from pipeline.parallel.scheduler import check_scheduler
from pipeline.workflow.ledger import Ledger, RunLock
from pipeline.workflow.plan import PlannedStack, fingerprint, plan_stacks
from pipeline.workflow.schema import Workflow

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------- runs
@dataclasses.dataclass
class RunSummary:
    """What a run did; ``failed`` lists (stack, error) of this run and of skipped
    stacks whose unchanged inputs failed before."""

    run_id: int
    planned: int
    skipped: list[str]
    done: list[str]
    failed: list[tuple[str, str]]
    seconds: float

    @property
    def ok(self) -> bool:
        return not self.failed


def _needs_run(
    record, fp: str, output: Path, retry_failed: bool, file_sha256: Callable[[Path], str]
) -> str | None:
    """Why a stack must be processed, or None when it is up to date."""
    if record is None:
        return "new"
    if record.fingerprint != fp:
        return "changed"
    if record.status == "done":
        sidecar = output.with_name(output.name + ".json")
        if not (output.is_file() and sidecar.is_file()):
            return "output missing"
        if record.output_sha256 and file_sha256(output) != record.output_sha256:
            return "output changed since it was written"
        return None
    if record.status == "failed" and record.error_kind == "input" and not retry_failed:
        return None
    return record.status  # interrupted, queued by a dead run, or a transient failure


def _remove_stale_temps(output: Path) -> None:
    """Temp files of atomic writes a killed run left behind (never complete outputs)."""
    for target in (output, output.with_name(output.name + ".json")):
        for temp in output.parent.glob(glob.escape(temp_prefix(target)) + "*.tmp"):
            temp.unlink(missing_ok=True)  # the run lock proves no other run writes here


def run_workflow(
    workflow: Workflow,
    *,
    dry_run: bool = False,
    on_plan: Callable[[list[tuple[PlannedStack, str]], int], None] | None = None,
    on_result: Callable[[dict], None] | None = None,
    on_progress: OnProgress | None = None,
    empty_ok: bool | None = None,
) -> RunSummary:
    """One incremental run: process new or changed stacks, record them in the ledger.

    Holds the output directory's :class:`~pipeline.workflow.ledger.RunLock` for the
    whole run (a second run is refused with
    :class:`~pipeline.workflow.ledger.LockedError`). ``on_plan(todo, skipped)`` is
    called once with the stacks to process and why.

    ``empty_ok`` (default: when the workflow has a ``[schedule]``; the CLI passes
    True for ``--every``/``--scheduled``): an input glob that matches nothing yet
    (an empty drop folder) is logged as "nothing to do yet" instead of an error.
    A run that ends early (lost scheduler, interrupt) closes its ledger run as
    ``interrupted``; its unfinished stacks are processed by the next run.
    """
    start = time.perf_counter()
    if empty_ok is None:
        empty_ok = workflow.every_s is not None
    # validates everything before any work
    planned = plan_stacks(workflow, empty_ok=empty_ok, on_empty=_nothing_yet)
    try:
        workflow.output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(
            f"{workflow.path}: cannot create the output directory {workflow.output_dir} ({err})"
        ) from err
    with (
        RunLock(workflow.output_dir, f"workflow {workflow.path}"),
        Ledger(workflow.ledger_path) as ledger,
    ):
        fps = {s.id: fingerprint(s, ledger.file_sha256) for s in planned}
        todo, skipped, still_failed = [], [], []
        for stack in planned:
            record = ledger.get(stack.id)
            reason = _needs_run(
                record, fps[stack.id], stack.output, workflow.retry_failed, ledger.file_sha256
            )
            if reason is not None:
                todo.append((stack, reason))
            elif record.status == "failed":
                still_failed.append((stack.id, f"{record.error} (unchanged; not retried)"))
            else:
                skipped.append(stack.id)
        if on_plan is not None:
            on_plan(todo, len(planned) - len(todo))
        if dry_run:
            return RunSummary(0, len(planned), skipped, [], still_failed, 0.0)
        if todo and workflow.scheduler:
            check_scheduler(workflow.scheduler)  # before the ledger says "running"
        run_id = ledger.start_run(str(workflow.path), workflow.scheduler)
        jobs = []
        for stack, _ in todo:
            stack.output.parent.mkdir(parents=True, exist_ok=True)
            _remove_stale_temps(stack.output)
            ledger.queue(run_id, stack.id, list(stack.paths), str(stack.output), fps[stack.id])
            jobs.append(BatchJob(stack.id, stack.paths, str(stack.output), stack.options))
        done: list[str] = []
        failed: list[tuple[str, str]] = []

        def record(result: dict) -> None:
            ledger.record(run_id, result)
            if result["status"] == "done":
                done.append(result["key"])
            else:
                failed.append((result["key"], result["error"]))
            if on_result is not None:
                on_result(result)

        try:
            run_batch(
                jobs,
                scheduler=workflow.scheduler,
                concurrency=workflow.concurrency,
                threads_per_stack=workflow.threads_per_stack,
                on_result=record,
                on_progress=on_progress,
            )
        except BaseException:
            ledger.abort_run(
                run_id,
                planned=len(planned),
                skipped=len(skipped),
                done=len(done),
                failed=len(failed) + len(still_failed),
            )
            raise
        failed += still_failed
        ledger.finish_run(
            run_id, planned=len(planned), skipped=len(skipped), done=len(done), failed=len(failed)
        )
    return RunSummary(run_id, len(planned), skipped, done, failed, time.perf_counter() - start)


def _nothing_yet(message: str) -> None:
    log.warning("nothing to do yet: %s", message)


def run_every(
    interval_s: float,
    run_once: Callable[[], bool],
    *,
    runs: int | None = None,
    stop: threading.Event | None = None,
    on_error: Callable[[Exception], None] | None = None,
) -> int:
    """Call ``run_once`` every ``interval_s`` seconds (start to start); return the run count.

    A run that overruns its interval is followed at once by the next (missed
    ticks are skipped, never queued). Errors of one run (an invalid workflow
    edit, a refused lock) go to ``on_error`` and the loop goes on; the first
    run's errors propagate.
    """
    stop = stop or threading.Event()
    count = 0
    next_start = time.monotonic()
    while not stop.is_set() and (runs is None or count < runs):
        try:
            run_once()
        except FlexdofError as err:
            if count == 0 or on_error is None:
                raise
            on_error(err)
        count += 1
        if runs is not None and count >= runs:
            break
        next_start += interval_s
        next_start = max(next_start, time.monotonic())  # overran: start the next one now
        stop.wait(max(0.0, next_start - time.monotonic()))
    return count
