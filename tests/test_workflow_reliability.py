"""Issue 16: workflow and scheduler reliability (transient failures, output hashes,
outputs inside the inputs, empty drop folders, schedulers that are not one or vanish).

Schedulers are real: a dask LocalCluster on 127.0.0.1, or ``dask scheduler`` and
``dask worker`` processes killed with SIGKILL mid-run. Every wait is bounded.
"""

from __future__ import annotations

import errno
import logging
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import distributed
import pytest
from test_batch import make_synthetic_stack

from pipeline.errors import InputError
from pipeline.jobs.batch import BatchJob, run_stack_task
from pipeline.parallel.scheduler import SchedulerError, check_scheduler
from pipeline.workflow.ledger import LEDGER_NAME
from pipeline.workflow.plan import NoInputsYet
from pipeline.workflow.run import run_workflow
from pipeline.workflow.schema import load_workflow

WORKFLOW = """
[[inputs]]
directories = "{glob}"
[options]
blur_span_px = 5.0
[output]
directory = "{out}"
name = "{{stack}}.tif"
[run]
concurrency = 1
{extra}
"""


def make_tree(root: Path, n: int = 3) -> Path:
    for i in range(n):
        make_synthetic_stack(root / "stacks" / f"s{i}", seed=i, frames=3, shape=(48, 64))
    return root


def workflow_file(root: Path, *, glob="stacks/*", out="out", extra="") -> Path:
    path = root / "flow.toml"
    path.write_text(WORKFLOW.format(glob=glob, out=out, extra=extra))
    return path


def ledger(out: Path, query: str) -> list[tuple]:
    with sqlite3.connect(f"file:{out / LEDGER_NAME}?mode=ro", uri=True) as db:
        return db.execute(query).fetchall()


def plan_of(flow: Path) -> dict[str, str]:
    seen: dict[str, str] = {}
    run_workflow(
        load_workflow(flow),
        dry_run=True,
        on_plan=lambda todo, n: seen.update({s.id: why for s, why in todo}),
    )
    return seen


# ---------------------------------------------------------------------- transient failures
def test_disk_full_failures_are_retried_on_the_next_run(tmp_path, monkeypatch):
    flow = workflow_file(make_tree(tmp_path))
    real_fsync = os.fsync

    def disk_full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", disk_full)
    first = run_workflow(load_workflow(flow))
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert len(first.failed) == 3 and not first.done
    for _stack, error in first.failed:  # the message names the file it could not write
        assert "/out/s" in error and "No space left on device" in error
    assert ledger(tmp_path / "out", "SELECT DISTINCT error_kind FROM stacks") == [("error",)]
    assert set(plan_of(flow).values()) == {"failed"}
    second = run_workflow(load_workflow(flow))  # space freed: the failed stacks are done
    assert sorted(second.done) == ["stacks/s0", "stacks/s1", "stacks/s2"] and second.ok


def test_a_valueerror_from_numpy_is_not_a_permanent_input_error(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise ValueError("operands could not be broadcast together")

    monkeypatch.setattr("pipeline.jobs.batch.process_stack", broken)
    result = run_stack_task(BatchJob("k", (str(tmp_path),), str(tmp_path / "o.tif")), 1)
    assert result["status"] == "failed" and result["error_kind"] == "error"
    # An input error stays permanent (not retried until the inputs change).
    monkeypatch.undo()
    result = run_stack_task(BatchJob("k", (str(tmp_path / "none"),), str(tmp_path / "o.tif")), 1)
    assert result["error_kind"] == "input"


# ---------------------------------------------------------------------- outputs
def test_an_output_corrupted_in_place_is_processed_again(tmp_path):
    flow = workflow_file(make_tree(tmp_path, 2))
    run_workflow(load_workflow(flow))
    out = tmp_path / "out" / "s1.tif"
    out.write_bytes(os.urandom(out.stat().st_size))  # same name, same size, garbage
    assert plan_of(flow) == {"stacks/s1": "output changed since it was written"}
    again = run_workflow(load_workflow(flow))
    assert again.done == ["stacks/s1"]
    assert plan_of(flow) == {}


def test_an_output_folder_inside_the_input_glob_is_not_a_stack(tmp_path):
    make_tree(tmp_path, 2)
    flow = workflow_file(tmp_path, out="stacks/results")
    first = run_workflow(load_workflow(flow))
    assert sorted(first.done) == ["stacks/s0", "stacks/s1"]
    second = run_workflow(load_workflow(flow))
    assert second.done == [] and second.failed == [] and len(second.skipped) == 2


# ---------------------------------------------------------------------- scheduled workflows
def test_an_empty_drop_folder_is_nothing_to_do_yet_for_a_scheduled_workflow(tmp_path, caplog):
    (tmp_path / "drop").mkdir()
    flow = workflow_file(tmp_path, glob="drop/*", extra='[schedule]\nevery = "15m"')
    with caplog.at_level(logging.WARNING):
        summary = run_workflow(load_workflow(flow))
    assert summary.ok and summary.planned == 0
    assert "nothing to do yet" in caplog.text and "drop/*" in caplog.text
    # Run once, without a schedule, an input that matches nothing is still an error.
    once = workflow_file(tmp_path, glob="drop/*")
    with pytest.raises(NoInputsYet, match="matches no directory"):
        run_workflow(load_workflow(once))
    assert run_workflow(load_workflow(once), empty_ok=True).ok  # what --every passes


# ---------------------------------------------------------------------- schedulers
@pytest.fixture(scope="module")
def cluster():
    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=1,
        processes=False,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address="127.0.0.1:0",
    ) as local_cluster:
        yield local_cluster


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timeout(60)
def test_a_dashboard_port_is_reported_as_not_a_scheduler_in_seconds(cluster):
    check_scheduler(cluster.scheduler_address)  # the real one passes
    port = cluster.dashboard_link.split(":")[2].split("/")[0]
    t0 = time.monotonic()
    with pytest.raises(SchedulerError, match=r"an HTTP server answered \(HTTP/1.1 "):
        check_scheduler(f"tcp://127.0.0.1:{port}")
    assert time.monotonic() - t0 < 15


@pytest.mark.timeout(60)
def test_a_banner_from_another_service_is_named(tmp_path):
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        import threading

        def serve():
            conn, _ = server.accept()
            with conn:
                conn.sendall(b"SSH-2.0-OpenSSH_9.6\r\n")
                time.sleep(0.5)

        thread = threading.Thread(target=serve, daemon=True)
        thread.start()
        with pytest.raises(SchedulerError, match=r"not a dask scheduler: it answered 'SSH-2.0"):
            check_scheduler(address)
        thread.join(5)


@pytest.mark.timeout(60)
def test_a_closed_port_fails_at_once_and_the_ledger_is_not_left_running(tmp_path):
    address = f"tcp://127.0.0.1:{_closed_port()}"
    flow = workflow_file(make_tree(tmp_path, 2), extra=f'scheduler = "{address}"')
    t0 = time.monotonic()
    with pytest.raises(SchedulerError, match="nothing listens on port"):
        run_workflow(load_workflow(flow))
    assert time.monotonic() - t0 < 5
    assert ledger(tmp_path / "out", "SELECT status FROM runs WHERE status='running'") == []
    assert ledger(tmp_path / "out", "SELECT * FROM stacks WHERE status='queued'") == []


def _dask(*args: str) -> subprocess.Popen:
    exe = Path(sys.executable).with_name("dask")
    return subprocess.Popen(
        [str(exe), *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True
    )


@pytest.mark.timeout(180)
def test_a_scheduler_killed_mid_run_is_one_error_and_the_stacks_are_redone(tmp_path):
    port = _closed_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = _dask("scheduler", "--host", "127.0.0.1", "--port", str(port),
                      "--no-dashboard")
    worker = None
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                check_scheduler(address, timeout_s=1)
                break
            except SchedulerError:
                assert time.monotonic() < deadline, "the scheduler did not start"
                time.sleep(0.5)
        worker = _dask("worker", address, "--nthreads", "1", "--nworkers", "1",
                       "--no-dashboard", "--host", "127.0.0.1")
        with distributed.Client(address, timeout="30s") as client:
            client.wait_for_workers(1, timeout=60)
        flow = workflow_file(make_tree(tmp_path, 4), extra=f'scheduler = "{address}"')
        killed = []

        def on_result(result):
            if not killed:
                scheduler.send_signal(signal.SIGKILL)
                killed.append(result["key"])

        t0 = time.monotonic()
        with pytest.raises(SchedulerError, match=r"lost the connection mid-run \(1 of 4"):
            run_workflow(load_workflow(flow), on_result=on_result)
        assert time.monotonic() - t0 < 90
    finally:
        for proc in (worker, scheduler):
            if proc is not None:
                proc.kill()
                proc.wait(30)
    out = tmp_path / "out"
    assert ledger(out, "SELECT status FROM runs") == [("interrupted",)]
    statuses = dict(ledger(out, "SELECT stack, status FROM stacks"))
    assert sorted(statuses.values()) == ["done", "interrupted", "interrupted", "interrupted"]
    # The next run (here on this machine) does the three unfinished stacks.
    local = workflow_file(tmp_path)
    again = run_workflow(load_workflow(local))
    assert len(again.done) == 3 and again.ok


def test_scheduler_address_without_port_is_an_input_error():
    with pytest.raises(InputError, match="give the port"):
        check_scheduler("tcp://127.0.0.1")


def test_an_interrupted_run_does_not_leave_the_ledger_running(tmp_path):
    flow = workflow_file(make_tree(tmp_path, 3))

    def interrupt(result):  # Ctrl-C, or SIGTERM with install_signal_cleanup
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_workflow(load_workflow(flow), on_result=interrupt)
    out = tmp_path / "out"
    assert ledger(out, "SELECT status FROM runs") == [("interrupted",)]
    assert ledger(out, "SELECT * FROM stacks WHERE status IN ('queued', 'running')") == []
    again = run_workflow(load_workflow(flow))
    assert again.ok and len(again.done) >= 2


def test_an_output_folder_above_the_inputs_excludes_nothing(tmp_path):
    make_tree(tmp_path, 2)
    flow = workflow_file(tmp_path, out=".")
    assert sorted(plan_of(flow)) == ["stacks/s0", "stacks/s1"]
    assert sorted(run_workflow(load_workflow(flow)).done) == ["stacks/s0", "stacks/s1"]
    assert plan_of(flow) == {}


FILES_WORKFLOW = """
[[inputs]]
files = "*.png"
group_by = '^(?P<stack>[a-z]+)_\\d+\\.png$'
[options]
blur_span_px = 5.0
[output]
directory = "."
name = "{stack}_edof.png"
"""


def test_file_groups_never_take_the_workflows_own_outputs(tmp_path):
    stack = make_synthetic_stack(tmp_path / "tmp", seed=1, frames=3, shape=(48, 64))
    for i, frame in enumerate(sorted(stack.iterdir())):
        frame.rename(tmp_path / f"abc_{i}.png")
    flow = tmp_path / "flow.toml"
    flow.write_text(FILES_WORKFLOW)
    assert run_workflow(load_workflow(flow)).done == [".#abc"]
    assert (tmp_path / "abc_edof.png.json").is_file()
    assert plan_of(flow) == {}  # abc_edof.png is not a frame of a new stack "abc_edof"


def test_dry_run_prints_its_plan_to_stdout_even_when_quiet(tmp_path, capsys):
    from pipeline.cli import main

    make_synthetic_stack(tmp_path / "stacks" / "a", seed=1, frames=3, shape=(40, 48))
    path = tmp_path / "wf.toml"
    path.write_text(
        '[[inputs]]\ndirectories = "stacks/*"\n[options]\nblur_span_px = 5.0\n'
        '[output]\ndirectory = "out"\n'
    )
    assert main(["workflow", "run", str(path), "--dry-run", "-q"]) == 0
    captured = capsys.readouterr()
    assert "1 stack(s) would process" in captured.out and "a" in captured.out
    assert "would process" not in captured.err
    assert not list((tmp_path / "out").glob("*.tif"))  # a dry run writes no result


def test_every_with_an_empty_drop_folder_is_nothing_to_do_yet(tmp_path):
    from pipeline.cli import main

    (tmp_path / "drop").mkdir()
    path = tmp_path / "wf.toml"
    path.write_text(
        '[[inputs]]\ndirectories = "drop/*"\n[options]\nblur_span_px = 5.0\n'
        '[output]\ndirectory = "out"\n'
    )
    assert main(["-q", "workflow", "run", str(path), "--every", "1s", "--runs", "1"]) == 0
    assert main(["-q", "workflow", "run", str(path)]) == 2  # a one-off run: still an error
