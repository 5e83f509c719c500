"""Workflow files, incremental runs, the SQLite ledger, the run lock and scheduling.

Runs are real: the CLI in a subprocess (killed with SIGKILL mid-run), a real
SQLite ledger read back with :mod:`sqlite3`, and downscaled copies of the real
stacks in ../shared/data alongside synthetic ones.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_batch import REAL_STACKS, copy_real_stack, make_synthetic_stack, sha256

from pipeline.cli import main
from pipeline.errors import InputError
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.workflow.ledger import LEDGER_NAME, Ledger, RunLock
from pipeline.workflow.plan import output_path, plan_stacks, safe_name
from pipeline.workflow.run import run_workflow
from pipeline.workflow.schema import load_workflow, parse_interval

REPO = Path(__file__).resolve().parents[1]


def write_workflow(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def ledger_rows(out: Path, query: str) -> list[tuple]:
    with sqlite3.connect(f"file:{out / LEDGER_NAME}?mode=ro", uri=True) as db:
        return db.execute(query).fetchall()


def check_outputs_complete(out: Path, shapes: dict[str, tuple]) -> int:
    """Every visible output image decodes fully with its stack's shape."""
    count = 0
    for image in out.glob("*.tif"):
        data = read_frame(image)
        assert data.shape == shapes[image.stem], image
        assert np.all(np.isfinite(data))
        count += 1
    return count


# ---------------------------------------------------------------------- validation
WORKFLOW_OK = """
[[inputs]]
directories = "stacks/*"
[options]
blur_span_px = 5.0
[output]
directory = "out"
"""


@pytest.fixture
def small_tree(tmp_path) -> Path:
    for name, seed in (("a", 1), ("b", 2)):
        make_synthetic_stack(tmp_path / "stacks" / name, seed=seed, frames=3, shape=(48, 64))
    return tmp_path


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (WORKFLOW_OK + "bogus = 1\n", "unknown key 'bogus'"),
        (WORKFLOW_OK.replace("blur_span_px = 5.0", "blur_span = 5.0"), "unknown key 'blur_span'"),
        (WORKFLOW_OK.replace("5.0", '"5"'), "blur_span_px in \\[options\\] must be a number"),
        (WORKFLOW_OK.replace("5.0", "-1.0"), "must be a finite number > 0"),
        (WORKFLOW_OK.replace("blur_span_px = 5.0", "white = 0"), "white in \\[options\\] must"),
        (WORKFLOW_OK + "[run]\nconcurrency = 0\n", "concurrency in \\[run\\] must be >= 1"),
        (WORKFLOW_OK + "[run]\nconcurrency = true\n", "must be an integer"),
        (WORKFLOW_OK + '[run]\nscheduler = "localhost"\n', "tcp://"),
        (WORKFLOW_OK + '[schedule]\nevery = "soon"\n', "not an interval"),
        (WORKFLOW_OK.replace('"stacks/*"', '"nothing/*"'), "matches no directory"),
        (
            '[[inputs]]\nfiles = "stacks/*/*.xyz"\n[output]\ndirectory = "o"\n',
            "matches no image files",
        ),
        ("[output]\ndirectory = 'out'\n", "at least one \\[\\[inputs\\]\\]"),
        (WORKFLOW_OK.replace('directory = "out"', ""), "missing key 'directory'"),
        (WORKFLOW_OK + 'name = "../{stack}.tif"\n', "inside the output directory"),
        (WORKFLOW_OK + 'name = "/tmp/{stack}.tif"\n', "inside the output directory"),
        (WORKFLOW_OK + 'name = "{stack}.bmp"\n', "must end in one of"),
        (WORKFLOW_OK + 'name = "fixed.tif"\n', "must contain \\{stack\\}"),
        (WORKFLOW_OK + 'name = "{user}.tif"\n', "uses \\{user\\}"),
        (WORKFLOW_OK + 'name = "{stack}.jpg"\nencoding = "float32"\n', "not available for .jpg"),
        (WORKFLOW_OK + 'name = "same.{stack}"[:0]\n', "not valid TOML"),
        (WORKFLOW_OK.replace("[options]", '[options]\nmethod = "magic"'), "method .* one of"),
        (WORKFLOW_OK.replace("[options]", '[options]\nlens = "no-such-lens"'), "lens"),
        (
            '[[inputs]]\ndirectories = "stacks/*"\ngroup_by = "x"\n[output]\ndirectory = "o"\n',
            "'group_by' .* needs 'files'",
        ),
        (
            '[[inputs]]\nfiles = "stacks/*/*.png"\ngroup_by = "(x"\n[output]\ndirectory = "o"\n',
            "not a regular expression",
        ),
        (
            '[[inputs]]\nfiles = "stacks/*/*.png"\ngroup_by = "frame"\n[output]\ndirectory = "o"\n',
            "\\(\\?P<stack>",
        ),
    ],
)
def test_invalid_workflows_are_refused_before_any_work(small_tree, text, match):
    path = write_workflow(small_tree / "wf.toml", text)
    with pytest.raises(InputError, match=match):
        plan_stacks(load_workflow(path))
    assert not (small_tree / "out").exists()  # nothing was started


def test_name_collision_is_refused(small_tree):
    make_synthetic_stack(small_tree / "more" / "a", seed=3, frames=3, shape=(48, 64))
    text = WORKFLOW_OK + '[[inputs]]\ndirectories = "more/*"\n'
    path = write_workflow(small_tree / "wf.toml", text)
    with pytest.raises(InputError, match=r"would both write .*parent"):
        plan_stacks(load_workflow(path))
    fixed = text.replace('directory = "out"', 'directory = "out"\nname = "{parent}-{stack}.tif"')
    outputs = [
        s.output.name
        for s in plan_stacks(load_workflow(write_workflow(small_tree / "wf.toml", fixed)))
    ]
    assert outputs == ["stacks-a.tif", "stacks-b.tif", "more-a.tif"]


def test_files_grouped_into_stacks_by_regex(tmp_path):
    source = make_synthetic_stack(tmp_path / "src", seed=4, frames=3, shape=(48, 64))
    shots = tmp_path / "shots"
    shots.mkdir()
    for prefix in ("left", "right"):
        for frame in sorted(source.iterdir()):
            (shots / f"{prefix}_{frame.name}").write_bytes(frame.read_bytes())
    path = write_workflow(
        tmp_path / "wf.toml",
        """
[[inputs]]
files = "shots/*.png"
group_by = '^(?P<stack>[a-z]+)_frame'
[output]
directory = "out"
name = "{stack}.png"
""",
    )
    planned = plan_stacks(load_workflow(path))
    assert [(s.id, s.output.name, len(s.paths)) for s in planned] == [
        ("shots#left", "left.png", 3),
        ("shots#right", "right.png", 3),
    ]


@given(st.text(min_size=1, max_size=40))
def test_output_names_from_inputs_never_escape(name):
    out = Path("/tmp/flexdof-out")
    path = output_path(out, "{parent}/{stack}.tif", stack=name, parent=name)
    assert path.resolve().is_relative_to(out.resolve())
    assert "/" not in safe_name(name) and not safe_name(name).startswith(".")


def test_symlink_escape_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "evil").symlink_to(tmp_path.parent)
    with pytest.raises(InputError, match="outside the output directory"):
        output_path(out, "{parent}/{stack}.tif", stack="x", parent="evil")


@pytest.mark.parametrize(
    ("text", "seconds"), [("90s", 90), ("15m", 900), ("1h30m", 5400), ("1d", 86400), ("45", 45)]
)
def test_parse_interval(text, seconds):
    assert parse_interval(text) == seconds


def test_shipped_examples_validate(repo_root):
    examples = sorted((repo_root / "workflows").glob("*.toml"))
    assert examples, "workflows/ ships no example"
    for example in examples:
        load_workflow(example)  # inputs may be absent on this machine; the schema must hold


# ---------------------------------------------------------------------- incremental runs
def test_changes_reprocess_affected_stacks_only(small_tree):
    make_synthetic_stack(small_tree / "other" / "c", seed=5, frames=3, shape=(48, 64))
    text = (
        WORKFLOW_OK + '[[inputs]]\ndirectories = "other/*"\n[inputs.options]\nblur_span_px = 4.0\n'
    )
    path = write_workflow(small_tree / "wf.toml", text)
    first = run_workflow(load_workflow(path))
    assert sorted(first.done) == ["other/c", "stacks/a", "stacks/b"] and first.ok
    assert run_workflow(load_workflow(path)).done == []  # idempotent

    write_workflow(path, text.replace("blur_span_px = 4.0", "blur_span_px = 3.0"))
    assert run_workflow(load_workflow(path)).done == ["other/c"]  # only that input's stacks

    frame = small_tree / "stacks" / "b" / "frame_01.png"
    os.utime(frame, (time.time() + 5, time.time() + 5))  # touched, content unchanged
    assert run_workflow(load_workflow(path)).done == []
    write_image(frame, np.full((48, 64), 0.5, np.float32))  # content changed
    assert run_workflow(load_workflow(path)).done == ["stacks/b"]

    (small_tree / "out" / "a.tif").unlink()  # an output deleted by hand is redone
    assert run_workflow(load_workflow(path)).done == ["stacks/a"]
    counts = dict(
        ledger_rows(
            small_tree / "out",
            "SELECT stack, COUNT(*) FROM attempts WHERE status='done' GROUP BY stack",
        )
    )
    assert counts == {"other/c": 2, "stacks/a": 2, "stacks/b": 2}


def test_bad_stacks_fail_alone_with_clear_errors(shared_data, tmp_path):
    root = tmp_path / "stacks"
    copy_real_stack(shared_data / "chimpstackr-beetle", "*.jpg", root / "good-beetle")
    make_synthetic_stack(root / "good-synthetic", seed=6, frames=3, shape=(48, 64))
    corrupt = copy_real_stack(shared_data / "shinestacker-amber", "*.jpg", root / "corrupt")
    victim = sorted(corrupt.iterdir())[2]
    victim.write_bytes(victim.read_bytes()[: victim.stat().st_size // 3])  # truncated JPEG
    (root / "empty").mkdir()
    mixed = make_synthetic_stack(root / "mixed", seed=7, frames=3, shape=(48, 64))
    write_image(mixed / "frame_03.png", np.full((40, 64), 0.5, np.float32))
    path = write_workflow(tmp_path / "wf.toml", WORKFLOW_OK)
    assert main(["-q", "workflow", "run", str(path)]) == 1
    errors = dict(
        ledger_rows(tmp_path / "out", "SELECT stack, error FROM stacks WHERE status='failed'")
    )
    assert set(errors) == {"stacks/corrupt", "stacks/empty", "stacks/mixed"}
    assert victim.name in errors["stacks/corrupt"]
    assert "no image files" in errors["stacks/empty"]
    assert "frame_03.png" in errors["stacks/mixed"] and "one size" in errors["stacks/mixed"]
    done = ledger_rows(tmp_path / "out", "SELECT stack FROM stacks WHERE status='done'")
    assert sorted(done) == [("stacks/good-beetle",), ("stacks/good-synthetic",)]
    assert sorted(p.name for p in (tmp_path / "out").glob("*.tif")) == [
        "good-beetle.tif",
        "good-synthetic.tif",
    ]

    # unchanged bad inputs are not retried, but still make the exit code say "failed"
    assert main(["-q", "workflow", "run", str(path)]) == 1
    (mixed / "frame_03.png").unlink()  # fixed: reprocessed on the next run
    assert main(["-q", "workflow", "run", str(path)]) == 1
    assert ledger_rows(
        tmp_path / "out", "SELECT status FROM stacks WHERE stack='stacks/mixed'"
    ) == [("done",)]
    assert ledger_rows(
        tmp_path / "out", "SELECT COUNT(*) FROM attempts WHERE stack='stacks/corrupt'"
    ) == [(1,)]


# ---------------------------------------------------------------------- kill -9 and the lock
def _cli(*args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "pipeline.cli", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        **kwargs,
    )


def test_killed_run_resumes_without_recomputing(shared_data, tmp_path, capsys):
    root = tmp_path / "stacks"
    shapes = {}
    for name, (folder, pattern) in REAL_STACKS.items():
        copy_real_stack(shared_data / folder, pattern, root / name)
        shapes[name] = read_frame(next((root / name).iterdir())).shape
    for i in range(3):
        make_synthetic_stack(root / f"synthetic-{i}", seed=10 + i, frames=4)
        shapes[f"synthetic-{i}"] = (96, 128)
    out = tmp_path / "out"
    path = write_workflow(
        tmp_path / "wf.toml",
        """
[[inputs]]
directories = "stacks/[bs]*"
[options]
blur_span_px = 6.0
[[inputs]]
directories = "stacks/[ap]*"        # blur span estimated from the frames
[output]
directory = "out"
[run]
concurrency = 1
""",
    )
    run = _cli("workflow", "run", str(path))
    done_at_kill = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and run.poll() is None:
            if (out / LEDGER_NAME).exists():
                check_outputs_complete(out, shapes)  # never a truncated output, even mid-run
                try:
                    done_at_kill = ledger_rows(out, "SELECT stack FROM stacks WHERE status='done'")
                except sqlite3.OperationalError:  # created, its tables not yet
                    time.sleep(0.05)
                    continue
                if len(done_at_kill) >= 2:
                    break
            time.sleep(0.05)
        assert run.poll() is None, "the run ended before it could be killed"

        second = main(["workflow", "run", str(path)])  # a concurrent run is refused
        assert second == 75
        assert "another run of this workflow is in progress" in capsys.readouterr().err

        os.killpg(run.pid, signal.SIGKILL)
    finally:
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGKILL)
        run.communicate()
    assert run.returncode == -signal.SIGKILL
    done_at_kill = ledger_rows(out, "SELECT stack FROM stacks WHERE status='done'")
    assert 2 <= len(done_at_kill) < len(shapes)
    check_outputs_complete(out, shapes)

    rerun = _cli("workflow", "run", str(path))
    stdout, stderr = rerun.communicate(timeout=300)
    assert rerun.returncode == 0, stderr
    assert f"{len(shapes) - len(done_at_kill)} done" in stdout
    assert check_outputs_complete(out, shapes) == len(shapes)
    assert not list(out.glob(".*.tmp"))  # stale temps of the killed run were cleaned up

    with Ledger(out / LEDGER_NAME) as ledger:
        runs = ledger.runs()
        assert [r["status"] for r in runs] == ["interrupted", "ok"]
        for record in ledger.records():
            attempts = ledger.attempts(record.stack)
            assert record.status == "done"
            assert [a["status"] for a in attempts].count("done") == 1  # done exactly once
            assert record.output_sha256 == sha256(Path(record.output))
            if (record.stack,) in done_at_kill:  # not recomputed by the second run
                assert [a["run_id"] for a in attempts] == [runs[0]["id"]]
            else:  # queued (or in flight) at the kill: finished by the second run
                assert [(a["run_id"], a["status"]) for a in attempts] == [
                    (runs[0]["id"], "interrupted"),
                    (runs[1]["id"], "done"),
                ]

    third = _cli("-q", "workflow", "run", str(path))
    assert third.communicate(timeout=120) and third.returncode == 0
    assert ledger_rows(out, "SELECT done, skipped FROM runs ORDER BY id DESC LIMIT 1") == [
        (0, len(shapes))
    ]
    status = _cli("workflow", "status", str(path))
    text, _ = status.communicate(timeout=60)
    assert status.returncode == 0 and text.count(" done ") == len(shapes)


def test_lock_is_released_by_a_dead_holder(tmp_path):
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            (
                "import sys, time; from pipeline.workflow.ledger import RunLock\n"
                f"with RunLock({str(tmp_path)!r}, 'test holder'):\n"
                "    print('locked', flush=True); time.sleep(60)"
            ),
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(Exception, match="test holder, pid"), RunLock(tmp_path, "me"):
            pass
    finally:
        holder.kill()
        holder.communicate()
    with RunLock(tmp_path, "me"):  # the kernel dropped the dead holder's flock
        pass


def test_every_loops_with_the_same_guarantees(small_tree, capsys):
    path = write_workflow(small_tree / "wf.toml", WORKFLOW_OK + '[schedule]\nevery = "1s"\n')
    start = time.monotonic()
    assert main(["workflow", "run", str(path), "--scheduled", "--runs", "2"]) == 0
    assert time.monotonic() - start >= 1.0
    runs = ledger_rows(small_tree / "out", "SELECT done, skipped, status FROM runs ORDER BY id")
    assert runs == [(2, 0, "ok"), (0, 2, "ok")]
    assert "every 1 s" in capsys.readouterr().err


# ---------------------------------------------------------------------- the ledger itself
def _hand_made_ledger(path: Path, schema: str) -> Path:
    """A ledger file as an earlier flexdof left it: only its ``meta`` table matters here."""
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        db.execute("INSERT INTO meta VALUES ('schema', ?)", (schema,))
    return path


def test_ledger_opens_schema_1_files_and_refuses_other_schemas_and_non_sqlite(tmp_path):
    with Ledger(_hand_made_ledger(tmp_path / "v1.sqlite", "1")) as ledger:
        assert ledger.runs() == [] and ledger.records() == []
    for schema in ("0", "2"):
        path = _hand_made_ledger(tmp_path / f"v{schema}.sqlite", schema)
        with pytest.raises(InputError, match=f"schema {schema}, this flexdof reads 1"):
            Ledger(path)
    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(b"not a database, " * 256)
    with pytest.raises(InputError, match="cannot open it as SQLite"):
        Ledger(garbage)


def test_ledger_round_trips_runs_stacks_and_attempts(tmp_path):
    path = tmp_path / LEDGER_NAME
    with Ledger(path) as ledger:
        local = ledger.start_run("wf.toml", None)
        for stack in ("a", "b"):
            ledger.queue(local, stack, [f"{stack}/1.png", f"{stack}/2.png"], f"{stack}.tif", "fp")
        ledger.record(local, {"key": "a", "status": "done", "timings": {"read": 1.5},
                              "seconds": 2.0, "worker": "w1", "output_sha256": "ab"})
        ledger.record(local, {"key": "b", "status": "failed", "error": "bad frame",
                              "error_kind": "input"})
        ledger.finish_run(local, planned=2, skipped=0, done=1, failed=1)
        remote = ledger.start_run("wf.toml", "tcp://10.0.0.1:8786")
        ledger.queue(remote, "b", ["b/1.png"], "b.tif", "fp2")
        ledger.abort_run(remote, planned=1, skipped=1, done=0, failed=0)
        a, b = ledger.get("a"), ledger.get("b")
        assert ledger.get("c") is None
        assert a.timings == {"read": 1.5} and a.inputs == ["a/1.png", "a/2.png"]
        assert (a.status, a.seconds, a.worker, a.output_sha256) == ("done", 2.0, "w1", "ab")
        assert (b.status, b.fingerprint, b.inputs, b.timings) == ("interrupted", "fp2",
                                                                  ["b/1.png"], None)
        with pytest.raises(dataclasses.FrozenInstanceError):
            a.status = "queued"  # records are snapshots, never edited in place
        assert [(r["stack"], r["status"]) for r in ledger.attempts("b")] == [
            ("b", "failed"), ("b", "interrupted")]
        assert len(ledger.attempts()) == 3
    # read back without the Ledger class
    assert ledger_rows(tmp_path, "SELECT scheduler, status, planned, done, failed FROM runs") == [
        ("local", "failed", 2, 1, 1), ("tcp://10.0.0.1:8786", "interrupted", 1, 0, 0)]
    assert ledger_rows(tmp_path, "SELECT stack, timings, error FROM stacks ORDER BY stack") == [
        ("a", '{"read": 1.5}', None), ("b", None, "bad frame")]


def test_a_transaction_that_raises_is_rolled_back(tmp_path):
    with Ledger(tmp_path / LEDGER_NAME) as ledger:
        with pytest.raises(KeyboardInterrupt), ledger._transaction():
            ledger._db.execute("INSERT INTO meta VALUES ('half', 'written')")
            raise KeyboardInterrupt  # Ctrl-C in the middle of a write
        run = ledger.start_run("wf.toml", None)  # a new transaction can begin
        assert [r["id"] for r in ledger.runs()] == [run]
    assert ledger_rows(tmp_path, "SELECT key FROM meta") == [("schema",)]


def test_hash_cache_answers_while_size_mtime_and_inode_match(tmp_path):
    import hashlib

    path = tmp_path / "frame.bin"
    path.write_bytes(b"A" * 100)
    with Ledger(tmp_path / LEDGER_NAME) as ledger:
        first = ledger.file_sha256(path)
        stat = path.stat()
        with open(path, "r+b") as fh:  # same size and inode; the mtime is put back below
            fh.write(b"B")
        os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
        assert ledger.file_sha256(path) == first == hashlib.sha256(b"A" * 100).hexdigest()


def test_run_lock_file_names_the_holder_and_is_emptied_on_release(tmp_path):
    import re
    import socket
    import stat

    lock_file = tmp_path / "flexdof-ledger.lock"
    lock_file.write_text("x" * 300)  # a longer text left by an earlier holder
    holder = f"me, pid {os.getpid()} on {socket.gethostname()}, since "
    with RunLock(tmp_path, "me"):
        text = lock_file.read_text()
        assert re.fullmatch(re.escape(holder) + r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d", text), text
        with pytest.raises(Exception, match=re.escape(f"in progress ({holder}")):
            with RunLock(tmp_path, "other"):  # a second open file: flock refuses it
                pass
    assert lock_file.read_bytes() == b""
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    with RunLock(fresh, "me"):
        pass
    assert stat.S_IMODE((fresh / lock_file.name).stat().st_mode) & 0o111 == 0  # not executable
