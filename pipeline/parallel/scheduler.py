"""Where dask graphs run (local threads or a ``dask.distributed`` cluster) and
per-task progress on local schedulers.
"""

from __future__ import annotations

import contextlib
import functools
import os
import socket
import struct
import time
from collections.abc import Callable

import dask
import dask.threaded
from dask.callbacks import Callback

from pipeline.core import validate
from pipeline.errors import FlexdofError, InputError


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
HANDSHAKE_TIMEOUT_S = 5.0  # connecting, then waiting for the scheduler's greeting
CONNECT_TIMEOUT = "10s"  # dask's own connection timeout, once the handshake passed


class SchedulerError(FlexdofError):
    """The dask scheduler cannot be reached, is not a dask scheduler, or was lost mid-run."""


def _host_port(address: str) -> tuple[str, str, int]:
    scheme, sep, rest = address.partition("://")
    if not sep:
        raise InputError(f"--scheduler {address}: give an address such as tcp://HOST:8786")
    host, colon, port = rest.rstrip("/").rpartition(":")
    if not colon or not port.isdigit() or not host:
        raise InputError(
            f"--scheduler {address}: give the port, e.g. {scheme}://{rest or 'HOST'}:8786"
        )
    return scheme, host.strip("[]"), int(port)


def _first_line(data: bytes) -> str:
    return data.split(b"\n", 1)[0].rstrip(b"\r")[:60].decode("ascii", errors="replace")


def _describe_reply(data: bytes) -> str:
    shown = _first_line(data)
    return f"it answered {shown!r}" if shown.isprintable() and shown else f"it sent {data[:16]!r}"


def check_scheduler(address: str, timeout_s: float = HANDSHAKE_TIMEOUT_S) -> None:
    """Make sure a dask scheduler answers at ``address`` (``tcp://HOST:PORT``), quickly.

    A dask scheduler greets every new connection with a small framed message; anything
    else (a closed port, an HTTP dashboard, an SSH server, silence) is reported in one
    line saying what answered, within about ``2 * timeout_s`` seconds. Only ``tcp://``
    addresses are probed (TLS and other transports go to dask directly).
    """
    scheme, host, port = _host_port(address)
    if scheme != "tcp":
        return
    where = f"--scheduler {address}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except socket.gaierror as err:
        raise SchedulerError(f"{where}: unknown host {host!r} ({err.strerror})") from err
    except ConnectionRefusedError as err:
        raise SchedulerError(
            f"{where}: nothing listens on port {port} of {host} (connection refused); "
            "is the scheduler running? (dask scheduler --port PORT)"
        ) from err
    except TimeoutError as err:
        raise SchedulerError(
            f"{where}: no answer from {host}:{port} within {timeout_s:g} s "
            "(a wrong address or a firewall)"
        ) from err
    except OSError as err:
        raise SchedulerError(f"{where}: cannot connect ({err.strerror or err})") from err
    with sock:
        data = b""
        try:
            sock.settimeout(timeout_s)
            deadline = time.monotonic() + timeout_s
            while len(data) < 16 and time.monotonic() < deadline:
                chunk = sock.recv(4096)
                if not chunk:
                    break
                data += chunk
        except TimeoutError:
            pass
        except OSError as err:
            raise SchedulerError(f"{where}: the connection failed ({err.strerror or err})") from err
        if len(data) >= 16:
            (total,) = struct.unpack("<Q", data[:8])
            (frames,) = struct.unpack("<Q", data[8:16])
            if 0 < total < 1 << 20 and 0 < frames < 64:
                return  # a dask comm frame: the scheduler's handshake
            raise SchedulerError(f"{where}: not a dask scheduler: {_describe_reply(data)}")
        if data:
            raise SchedulerError(f"{where}: not a dask scheduler: {_describe_reply(data)}")
        try:  # silent: a server that waits for the client to speak first, e.g. HTTP
            sock.sendall(f"GET / HTTP/1.0\r\nHost: {host}\r\n\r\n".encode())
            reply = sock.recv(4096)
        except OSError:
            reply = b""
    if reply.startswith(b"HTTP/"):
        raise SchedulerError(
            f"{where}: an HTTP server answered ({_first_line(reply)}), not a dask "
            "scheduler: the dashboard? the scheduler's own port is usually 8786"
        )
    raise SchedulerError(
        f"{where}: {host}:{port} accepted the connection but sent no dask greeting within "
        f"{timeout_s:g} s: not a dask scheduler"
    )


@contextlib.contextmanager
def scheduler_context(scheduler: str | None = None, threads: int | None = None):
    """Local threads (default) or a dask.distributed cluster at ``scheduler`` (tcp://...)."""
    if threads is not None:
        validate.whole("--threads", threads)
    if scheduler:
        from distributed import Client

        check_scheduler(scheduler)
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT, set_as_default=False)
        except (OSError, TimeoutError) as err:
            raise SchedulerError(f"--scheduler {scheduler}: cannot connect ({err})") from err
        with client, dask.config.set(scheduler=client):
            yield
    else:
        with dask.config.set(scheduler=local_threads(threads), num_workers=threads):
            yield


def local_threads(threads: int | None = None) -> Callable:
    """dask's threaded scheduler on ``threads`` threads (all cores when None).

    Given as a function rather than the name ``"threads"``: dask resolves a scheduler
    *name* by importing ``distributed`` to look for a client, which costs ~0.3 s of
    every single-stack run that never uses one.
    """
    return functools.partial(dask.threaded.get, num_workers=threads)


def local_workers() -> int:
    """Threads a job may use outside dask graphs: ``--threads``, else one per core."""
    return int(dask.config.get("num_workers", None) or os.cpu_count() or 1)
