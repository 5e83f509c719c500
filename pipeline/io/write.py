"""Writing results atomically (temporary file + rename): images (16-bit sRGB or linear
TIFF, float32 TIFF, 8-bit PNG/JPEG) and JSON sidecars.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import glob
import io
import itertools
import json
import logging
import os
import re
import signal
import socket
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import tifffile

from pipeline.core.colour import linear_to_srgb
from pipeline.errors import InputError
from pipeline.io.exif import _insert_jpeg_exif, _insert_png_exif
from pipeline.io.icc import insert_jpeg_icc, insert_png_icc
from pipeline.io.probe import JPEG_EXTENSIONS, TIFF_EXTENSIONS

log = logging.getLogger(__name__)

# write_image: allowed encodings per extension, the first one is the default.
WRITE_ENCODINGS = {
    ".tif": ("srgb16", "linear16", "float32", "srgb8"),
    ".tiff": ("srgb16", "linear16", "float32", "srgb8"),
    ".png": ("srgb8", "srgb16"),
    ".jpg": ("srgb8",),
    ".jpeg": ("srgb8",),
}
JPEG_QUALITY = 95
QUANTISE_THREADS = min(4, os.cpu_count() or 1)  # row blocks encoded side by side

_TIFF_MARK = "flexdof transfer={}"


# --- writing ---------------------------------------------------------------------------------

_UMASK = os.umask(0)  # the process umask, read once (setting it is the only way to read it)
os.umask(_UMASK)


_LIVE_TEMPS: set[Path] = set()  # temporaries of this process not yet renamed or removed
_LIVE_LOCK = threading.Lock()
_HOST = re.sub(r"[^A-Za-z0-9]+", "", socket.gethostname())[:32] or "host"
_TEMP_TAG = "flexdof-{host}-{pid}"
_TEMP_RE = re.compile(r"\.flexdof-(?P<host>[A-Za-z0-9]*)-(?P<pid>\d+)\.[^.]*\.tmp$")
_NAME_IN_TEMP = 100  # characters of the target's name kept in its temporary's name


def temp_prefix(path: Path) -> str:
    """How the names of ``path``'s temporaries begin."""
    return f".{path.name[:_NAME_IN_TEMP]}."


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temps(path: str | Path) -> list[Path]:
    """Remove temporaries of ``path`` left by a killed flexdof process (SIGKILL, power loss).

    Only files this code can prove are its own and abandoned are removed: named
    ``.NAME.flexdof-HOST-PID.XXXX.tmp`` with this host's name and the id of a
    process that no longer runs.
    """
    p = Path(path)
    removed = []
    try:
        candidates = list(p.parent.glob(glob.escape(temp_prefix(p)) + "flexdof-*.tmp"))
    except OSError:
        return removed
    for temp in candidates:
        match = _TEMP_RE.search(temp.name)
        if match is None or match["host"] != _HOST or temp in _LIVE_TEMPS:
            continue
        pid = int(match["pid"])
        if pid == os.getpid() or _pid_alive(pid):
            continue
        with contextlib.suppress(OSError):
            temp.unlink()
            removed.append(temp)
            log.info("removed %s, left by a killed flexdof process (pid %d)", temp, pid)
    return removed


def _new_temp(path: Path) -> tuple[int, Path]:
    """An open temporary file beside ``path``, registered for cleanup on SIGTERM."""
    prefix = temp_prefix(path) + _TEMP_TAG.format(host=_HOST, pid=os.getpid()) + "."
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=prefix, suffix=".tmp")
    except OSError as err:
        raise OutputError(f"{path}: cannot write here ({_reason(err)})") from err
    with _LIVE_LOCK:
        _LIVE_TEMPS.add(Path(tmp))
    return fd, Path(tmp)


def _forget(tmp: Path, *, unlink: bool) -> None:
    with _LIVE_LOCK:
        _LIVE_TEMPS.discard(tmp)
    if unlink:
        tmp.unlink(missing_ok=True)


def _reason(err: OSError) -> str:
    return err.strerror or str(err) if isinstance(err, OSError) else str(err)


class OutputError(InputError):
    """An output could not be written (disk full, permissions, name too long).

    ``transient`` is True when a retry may succeed without changing the inputs
    (no space left, I/O error, quota): workflows retry such stacks on the next run.
    """

    def __init__(self, message: str, *, transient: bool = False) -> None:
        super().__init__(message)
        self.transient = transient


_TRANSIENT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EAGAIN, errno.EINTR})


def _output_error(path: Path, err: OSError, what: str = "cannot write it") -> OutputError:
    return OutputError(
        f"{path}: {what} ({_reason(err)})", transient=err.errno in _TRANSIENT_ERRNOS
    )


def stage_bytes(path: str | Path, payload: bytes) -> Path:
    """Write ``payload`` to a temporary file beside ``path`` (fsynced); return the temporary.

    Rename it into place with :func:`commit`, or drop it with :func:`discard`.
    """
    p = Path(path)
    remove_stale_temps(p)
    fd, tmp = _new_temp(p)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
    except BaseException as err:
        _forget(tmp, unlink=True)
        if isinstance(err, OSError):
            raise _output_error(p, err) from err
        raise
    return tmp


def discard(temps) -> None:
    """Remove staged temporaries that will not be committed."""
    for tmp in temps:
        _forget(Path(tmp), unlink=True)


def commit(pairs) -> None:
    """Rename staged ``(temporary, target)`` pairs into place, in order.

    Result sets are committed so that a reader never sees a new image with an
    old sidecar: the old sidecar is removed first, the sidecar comes last.
    """
    pairs = list(pairs)
    try:
        for tmp, target in pairs:
            os.replace(tmp, target)
            _forget(Path(tmp), unlink=False)
    except OSError as err:
        discard(tmp for tmp, _ in pairs)
        raise _output_error(Path(target), err) from err
    except BaseException:
        discard(tmp for tmp, _ in pairs)
        raise


def _atomic_write_bytes(path: Path, payload: bytes) -> None:
    """Write ``payload`` to a temporary file beside ``path``, then ``os.replace`` it."""
    commit([(stage_bytes(path, payload), path)])


def check_writable(path: str | Path, what: str = "output") -> None:
    """Refuse, before any work, an output that cannot be written: a folder, a missing or
    read-only folder, a name too long for the file system (its temporary's too)."""
    p = Path(path)
    if not p.parent.is_dir():
        raise OutputError(f"{what} {p}: the folder {p.parent} does not exist")
    try:
        name_max = os.pathconf(p.parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    longest = max(len(p.name.encode()), len((p.name + ".json").encode()))
    if longest > name_max:
        raise OutputError(
            f"{what} {p.name[:40]}...: the file name is {longest} bytes long; "
            f"{p.parent} allows at most {name_max}"
        )
    for target in (p, p.with_name(p.name + ".json")):
        if target.is_dir():
            raise OutputError(f"{what} {target} is a folder; give another file name")
    fd, tmp = _new_temp(p)  # the folder takes a new file (not read-only, not full of inodes)
    os.close(fd)
    _forget(tmp, unlink=True)


def cleanup_temps() -> None:
    """Remove every temporary this process is writing (a SIGTERM or an exit mid-write)."""
    with _LIVE_LOCK:
        temps = list(_LIVE_TEMPS)
        _LIVE_TEMPS.clear()
    for tmp in temps:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _on_sigterm(signum, frame) -> None:
    cleanup_temps()
    raise KeyboardInterrupt(f"signal {signum}")


def install_signal_cleanup() -> None:
    """Handle SIGTERM (``kill``, ``systemctl stop``) like Ctrl-C: temporaries are removed
    and :class:`KeyboardInterrupt` is raised in the main thread. Call it once, from the
    main thread, before a job starts (the CLI does)."""
    signal.signal(signal.SIGTERM, _on_sigterm)
    atexit.register(cleanup_temps)


def _json_default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def write_json(path: str | Path, obj: object) -> None:
    """Write ``obj`` as indented JSON, atomically (numpy values and Paths allowed).

    NaN and infinities are refused (JSON has none): :class:`InputError`.
    """
    _atomic_write_bytes(Path(path), encode_json(path, obj))


def encode_json(path: str | Path, obj: object) -> bytes:
    """``obj`` as the bytes :func:`write_json` writes."""
    p = Path(path)
    try:
        text = json.dumps(obj, indent=2, allow_nan=False, default=_json_default)
    except (TypeError, ValueError) as err:
        raise InputError(f"{p}: cannot encode the result as JSON: {err}") from err
    return (text + "\n").encode("utf-8")


def _quantise(image: np.ndarray, bits: int, transfer: str, path: Path) -> np.ndarray:
    """Clip to [0, 1] (logged), encode and round to ``bits``-bit integers.

    Elementwise, so the rows are encoded in up to ``QUANTISE_THREADS`` blocks of at least
    256 rows side by side (numpy and OpenCV release the GIL): one third of the write's time
    on a 3 Mpx image (issue 15); a smaller image is encoded in one pass, without a pool.
    """
    out = np.empty(image.shape, np.uint8 if bits == 8 else np.uint16)
    threads = min(QUANTISE_THREADS, max(1, image.shape[0] // 256))  # no pool for small images
    edges = np.linspace(0, image.shape[0], threads + 1).astype(int)
    blocks = [slice(a, b) for a, b in itertools.pairwise(edges) if b > a]

    def encode(rows: slice) -> int:
        part = image[rows]
        clipped = np.clip(part, 0.0, 1.0)
        outside = int(np.count_nonzero(clipped != part))
        if transfer == "srgb":
            clipped = linear_to_srgb(clipped)
        out[rows] = np.rint(clipped * (2**bits - 1))
        return outside

    if len(blocks) == 1:
        outside = encode(blocks[0])
    else:
        with ThreadPoolExecutor(len(blocks), thread_name_prefix="flexdof-encode") as pool:
            outside = sum(pool.map(encode, blocks))
    if outside:
        log.info("%s: clipped %d of %d values to [0, 1] for encoding", path, outside, image.size)
    return out


def _check_image(image: np.ndarray, path: Path) -> np.ndarray:
    arr = np.asarray(image)
    if arr.dtype.kind != "f":
        raise InputError(
            f"{path}: write_image expects float linear light, got dtype {arr.dtype}; "
            "convert with astype(np.float32) and scale to [0, 1]"
        )
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)) or 0 in arr.shape:
        raise InputError(f"{path}: image shape {arr.shape} is not (rows, cols) or (rows, cols, 3)")
    if not np.all(np.isfinite(arr)):
        raise InputError(
            f"{path}: image contains {int(np.count_nonzero(~np.isfinite(arr)))} NaN/Inf "
            "values; fix the computation (nothing was written)"
        )
    return arr


def write_image(
    path: str | Path,
    image: np.ndarray,
    *,
    encoding: str | None = None,
    exif: bytes | None = None,
    icc: bytes | None = None,
) -> None:
    """Encode a float linear-light image and write it atomically.

    Parameters
    ----------
    path : str or Path
        Output file; the format comes from the extension (.tif/.tiff, .png,
        .jpg/.jpeg).
    image : ndarray
        Float linear light, ``(rows, cols)`` or ``(rows, cols, 3)``; NaN/Inf
        are refused.
    encoding : str, optional
        TIFF: ``"srgb16"`` (default), ``"linear16"``, ``"float32"`` (linear,
        unclipped) or ``"srgb8"``; PNG: ``"srgb8"`` (default) or ``"srgb16"``;
        JPEG: ``"srgb8"`` (quality 95).
    exif : bytes, optional
        An EXIF block as :func:`read_exif` returns it; carried into JPEG (APP1)
        and PNG (eXIf). TIFF output does not carry it (logged).
    icc : bytes, optional
        An ICC profile (:func:`pipeline.io.icc.read_icc`); carried into sRGB-coded outputs
        (JPEG APP2, PNG iCCP, TIFF InterColorProfile); linear TIFFs carry none (logged).

    Notes
    -----
    Integer encodings clip to [0, 1] (the number of clipped values is logged
    at INFO) and round to the nearest code. The file is written to a
    temporary file in the same directory and renamed over ``path``, so on any
    error no partial file is left and an existing file stays intact.
    """
    payload = encode_image(path, image, encoding=encoding, exif=exif, icc=icc)
    _atomic_write_bytes(Path(path), payload)


def encode_image(
    path: str | Path,
    image: np.ndarray,
    *,
    encoding: str | None = None,
    exif: bytes | None = None,
    icc: bytes | None = None,
) -> bytes:
    """The bytes :func:`write_image` writes (the format from ``path``'s extension)."""
    p = Path(path)
    icc = icc or None  # an empty profile is none
    ext = p.suffix.lower()
    if ext not in WRITE_ENCODINGS:
        raise InputError(
            f"{p}: cannot write extension {p.suffix!r}; use one of {', '.join(WRITE_ENCODINGS)}"
        )
    allowed = WRITE_ENCODINGS[ext]
    enc = allowed[0] if encoding is None else encoding
    if enc not in allowed:
        raise InputError(
            f"{p}: encoding {encoding!r} is not available for {ext}; "
            f"use one of {', '.join(allowed)}"
        )
    arr = _check_image(image, p)
    bits = 8 if enc == "srgb8" else 16
    if ext in TIFF_EXTENSIONS:
        if enc == "float32":
            data, transfer = arr.astype(np.float32), "linear"
        else:
            transfer = "linear" if enc == "linear16" else "srgb"
            data = _quantise(arr, bits, transfer, p)
        if exif is not None:
            log.info("%s: EXIF is not carried into TIFF output", p)
        if icc is not None and transfer == "linear":
            log.info("%s: the frames' ICC profile is not carried into linear output", p)
            icc = None
        buffer = io.BytesIO()
        tifffile.imwrite(
            buffer,
            data,
            photometric="rgb" if data.ndim == 3 else "minisblack",
            description=_TIFF_MARK.format(transfer),
            software="flexdof",
            metadata=None,
            iccprofile=icc,
        )
        payload = buffer.getvalue()
    else:
        codes = _quantise(arr, bits, "srgb", p)
        if codes.ndim == 3:
            codes = np.ascontiguousarray(codes[:, :, ::-1])  # RGB -> BGR for OpenCV
        params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if ext in JPEG_EXTENSIONS else []
        try:
            ok, encoded = cv2.imencode(ext, codes, params)
        except cv2.error as err:
            raise InputError(f"{p}: OpenCV cannot encode the image: {err}") from err
        if not ok:
            raise InputError(f"{p}: OpenCV cannot encode a {arr.shape} image as {ext}")
        payload = encoded.tobytes()
        if icc is not None:  # before EXIF goes in after SOI: APP1, then APP2
            payload = insert_jpeg_icc(payload, icc) if ext in JPEG_EXTENSIONS else (
                insert_png_icc(payload, icc, p)
            )
        if exif is not None:
            insert = _insert_jpeg_exif if ext in JPEG_EXTENSIONS else _insert_png_exif
            payload = insert(payload, exif, p)
    return payload
