"""The ledger of a workflow's runs (SQLite in the output directory) and the run lock.

The ledger records, per stack, its input fingerprint, status, timings, output
and error, and every attempt of every run; it is what makes workflow runs
incremental and idempotent. Only the driver process writes it (workers return
their results as data), each change in its own transaction, so a run killed at
any moment leaves a consistent ledger: stacks it had queued are marked
``interrupted`` by the next run, which processes them again.

The lock is an advisory ``flock`` on a file beside the ledger: the kernel drops
it when the holding process dies (even by SIGKILL), so there are no stale locks.
It needs a local file system (or one with working ``flock``, e.g. NFSv4).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import socket
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path

from pipeline.errors import FlexdofError, InputError
from pipeline.io.hashing import sha256_file

LEDGER_NAME = "flexdof-ledger.sqlite"
LOCK_NAME = "flexdof-ledger.lock"
SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    workflow TEXT NOT NULL, host TEXT, pid INTEGER, scheduler TEXT,
    started REAL NOT NULL, finished REAL, status TEXT NOT NULL,
    planned INTEGER DEFAULT 0, skipped INTEGER DEFAULT 0,
    done INTEGER DEFAULT 0, failed INTEGER DEFAULT 0
);
CREATE TABLE IF NOT EXISTS stacks (
    stack TEXT PRIMARY KEY,
    inputs TEXT NOT NULL, output TEXT NOT NULL, fingerprint TEXT NOT NULL,
    status TEXT NOT NULL, error TEXT, error_kind TEXT,
    started REAL, finished REAL, seconds REAL, timings TEXT,
    output_sha256 TEXT, worker TEXT, run_id INTEGER, updated REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS attempts (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id INTEGER NOT NULL, stack TEXT NOT NULL, fingerprint TEXT NOT NULL,
    status TEXT NOT NULL, error TEXT, started REAL, finished REAL, seconds REAL, worker TEXT
);
CREATE TABLE IF NOT EXISTS file_hashes (
    path TEXT PRIMARY KEY, size INTEGER NOT NULL, mtime_ns INTEGER NOT NULL,
    inode INTEGER NOT NULL, sha256 TEXT NOT NULL
);
"""

#: Stack statuses: ``queued`` (submitted by a run), ``done``, ``failed``,
#: ``interrupted`` (queued by a run that ended before the stack finished).
STATUSES = ("queued", "done", "failed", "interrupted")


@dataclasses.dataclass(frozen=True)
class StackRecord:
    """One row of the ``stacks`` table."""

    stack: str
    inputs: list[str]
    output: str
    fingerprint: str
    status: str
    error: str | None
    error_kind: str | None
    started: float | None
    finished: float | None
    seconds: float | None
    timings: dict | None
    output_sha256: str | None
    worker: str | None
    run_id: int | None


class Ledger:
    """The SQLite ledger of one output directory.

    Parameters
    ----------
    path : Path
        The database file (created with its tables if missing).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        try:
            self._db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            self._db.row_factory = sqlite3.Row
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            with self._transaction():
                for statement in _SCHEMA.split(";"):
                    if statement.strip():
                        self._db.execute(statement)
                found = self._db.execute("SELECT value FROM meta WHERE key='schema'").fetchone()
                if found is None:
                    self._db.execute(
                        "INSERT INTO meta VALUES ('schema', ?)", (str(SCHEMA_VERSION),)
                    )
                elif int(found["value"]) != SCHEMA_VERSION:
                    raise InputError(
                        f"ledger {self.path}: schema {found['value']}, this flexdof reads "
                        f"{SCHEMA_VERSION}; use a new output directory"
                    )
        except sqlite3.Error as err:
            raise InputError(f"ledger {self.path}: cannot open it as SQLite ({err})") from err

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Ledger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @contextlib.contextmanager
    def _transaction(self) -> Iterator[None]:
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    # ------------------------------------------------------------------ runs
    def start_run(self, workflow: str, scheduler: str | None) -> int:
        """Open a run; stacks left ``queued`` by earlier (dead) runs become ``interrupted``.

        Call it while holding the :class:`RunLock`: then no other run is alive.
        """
        now = time.time()
        with self._transaction():
            self._db.execute("UPDATE attempts SET status='interrupted' WHERE status='queued'")
            self._db.execute(
                "UPDATE stacks SET status='interrupted', updated=? WHERE status='queued'", (now,)
            )
            self._db.execute("UPDATE runs SET status='interrupted' WHERE status='running'")
            cursor = self._db.execute(
                "INSERT INTO runs (workflow, host, pid, scheduler, started, status) "
                "VALUES (?, ?, ?, ?, ?, 'running')",
                (workflow, socket.gethostname(), os.getpid(), scheduler or "local", now),
            )
        return int(cursor.lastrowid)

    def finish_run(self, run_id: int, *, planned: int, skipped: int, done: int, failed: int):
        status = "failed" if failed else "ok"
        with self._transaction():
            self._db.execute(
                "UPDATE runs SET finished=?, status=?, planned=?, skipped=?, done=?, failed=? "
                "WHERE id=?",
                (time.time(), status, planned, skipped, done, failed, run_id),
            )

    def abort_run(self, run_id: int, *, planned: int, skipped: int, done: int, failed: int):
        """Close a run that ended early (lost scheduler, Ctrl-C, a crash): its stacks still
        queued become ``interrupted`` (processed again by the next run), the run too."""
        now = time.time()
        with self._transaction():
            self._db.execute(
                "UPDATE attempts SET status='interrupted' WHERE status='queued' AND run_id=?",
                (run_id,),
            )
            self._db.execute(
                "UPDATE stacks SET status='interrupted', updated=? "
                "WHERE status='queued' AND run_id=?",
                (now, run_id),
            )
            self._db.execute(
                "UPDATE runs SET finished=?, status='interrupted', planned=?, skipped=?, done=?, "
                "failed=? WHERE id=?",
                (now, planned, skipped, done, failed, run_id),
            )

    def runs(self) -> list[dict]:
        return [dict(row) for row in self._db.execute("SELECT * FROM runs ORDER BY id")]

    # ------------------------------------------------------------------ stacks
    def get(self, stack: str) -> StackRecord | None:
        row = self._db.execute("SELECT * FROM stacks WHERE stack=?", (stack,)).fetchone()
        return None if row is None else _record(row)

    def records(self) -> list[StackRecord]:
        return [_record(row) for row in self._db.execute("SELECT * FROM stacks ORDER BY stack")]

    def attempts(self, stack: str | None = None) -> list[dict]:
        query, args = "SELECT * FROM attempts ORDER BY id", ()
        if stack is not None:
            query, args = "SELECT * FROM attempts WHERE stack=? ORDER BY id", (stack,)
        return [dict(row) for row in self._db.execute(query, args)]

    def queue(self, run_id: int, stack: str, inputs: list[str], output: str, fp: str) -> None:
        """Record that ``run_id`` submitted ``stack`` (fingerprint ``fp``)."""
        now = time.time()
        with self._transaction():
            self._db.execute(
                "INSERT INTO stacks (stack, inputs, output, fingerprint, status, run_id, updated) "
                "VALUES (?, ?, ?, ?, 'queued', ?, ?) ON CONFLICT(stack) DO UPDATE SET "
                "inputs=excluded.inputs, output=excluded.output, "
                "fingerprint=excluded.fingerprint, status='queued', run_id=excluded.run_id, "
                "updated=excluded.updated",
                (stack, json.dumps(inputs), output, fp, run_id, now),
            )
            self._db.execute(
                "INSERT INTO attempts (run_id, stack, fingerprint, status) "
                "VALUES (?, ?, ?, 'queued')",
                (run_id, stack, fp),
            )

    def record(self, run_id: int, result: dict) -> None:
        """Store a finished stack (a :func:`pipeline.jobs.batch.run_stack_task` result)."""
        stack = result["key"]
        status = result["status"]
        fields = (
            status,
            result.get("error"),
            result.get("error_kind"),
            result.get("started"),
            result.get("finished"),
            result.get("seconds"),
            json.dumps(result.get("timings")) if result.get("timings") is not None else None,
            result.get("output_sha256"),
            result.get("worker"),
        )
        with self._transaction():
            self._db.execute(
                "UPDATE stacks SET status=?, error=?, error_kind=?, started=?, finished=?, "
                "seconds=?, timings=?, output_sha256=?, worker=?, updated=? "
                "WHERE stack=? AND run_id=?",
                (*fields, time.time(), stack, run_id),
            )
            self._db.execute(
                "UPDATE attempts SET status=?, error=?, started=?, finished=?, seconds=?, "
                "worker=? WHERE run_id=? AND stack=? AND status='queued'",
                (
                    status,
                    result.get("error"),
                    result.get("started"),
                    result.get("finished"),
                    result.get("seconds"),
                    result.get("worker"),
                    run_id,
                    stack,
                ),
            )

    # ------------------------------------------------------------------ content hashes
    def file_sha256(self, path: Path) -> str:
        """SHA-256 of a file's content, cached by (size, mtime_ns, inode).

        A file whose size, modification time and inode are unchanged is taken as
        unchanged (as git and rsync do); anything else is hashed again.
        """
        resolved = str(Path(path).resolve())
        stat = os.stat(resolved)
        key = (stat.st_size, stat.st_mtime_ns, stat.st_ino)
        row = self._db.execute(
            "SELECT size, mtime_ns, inode, sha256 FROM file_hashes WHERE path=?", (resolved,)
        ).fetchone()
        if row is not None and (row["size"], row["mtime_ns"], row["inode"]) == key:
            return str(row["sha256"])
        digest = sha256_file(Path(resolved))
        with self._transaction():
            self._db.execute(
                "INSERT OR REPLACE INTO file_hashes VALUES (?, ?, ?, ?, ?)",
                (resolved, *key, digest),
            )
        return digest


def _record(row: sqlite3.Row) -> StackRecord:
    return StackRecord(
        stack=row["stack"],
        inputs=json.loads(row["inputs"]),
        output=row["output"],
        fingerprint=row["fingerprint"],
        status=row["status"],
        error=row["error"],
        error_kind=row["error_kind"],
        started=row["started"],
        finished=row["finished"],
        seconds=row["seconds"],
        timings=json.loads(row["timings"]) if row["timings"] else None,
        output_sha256=row["output_sha256"],
        worker=row["worker"],
        run_id=row["run_id"],
    )


# ---------------------------------------------------------------------- run lock
class LockedError(FlexdofError):
    """Another run of the workflow holds the lock."""


class RunLock:
    """An exclusive, non-blocking lock on an output directory (``flock``).

    Parameters
    ----------
    directory : Path
        The workflow's output directory (holds the ledger).
    holder : str
        Who takes it (written into the lock file for the refusal message).
    """

    def __init__(self, directory: Path, holder: str) -> None:
        self.path = Path(directory) / LOCK_NAME
        self.holder = holder
        self._fd: int | None = None

    def __enter__(self) -> RunLock:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as err:
            try:
                who = os.read(fd, 4096).decode("utf-8", "replace").strip()
            finally:
                os.close(fd)
            raise LockedError(
                f"another run of this workflow is in progress ({who or 'unknown holder'}); "
                f"lock {self.path}. Wait for it to finish (it is released when that process "
                "exits)"
            ) from err
        os.ftruncate(fd, 0)
        text = f"{self.holder}, pid {os.getpid()} on {socket.gethostname()}, since "
        text += time.strftime("%Y-%m-%d %H:%M:%S")
        os.pwrite(fd, text.encode("utf-8"), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            os.ftruncate(self._fd, 0)
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None
