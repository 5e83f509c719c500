"""Replay a recorded ``gphoto2 --debug`` log as a pyusb backend (``usb.backend.IBackend``).

A ``gphoto2 --debug`` log of a real camera holds a hex dump of every USB bulk
transfer: the PTP command containers the host wrote and the data/response
containers the camera answered with. :func:`load_recording` parses those dumps
back into transactions (its own parser; no libgphoto2 code), and
:class:`ReplayBackend` plays them back: ``usb.core.find(backend=ReplayBackend(rec))``
gives a real ``usb.core.Device``, and the project's transport, session and
vendor drivers talk to it exactly as to a camera. Every command the host sends
is answered with the recorded data phase and response of a recorded
transaction with the same operation code and parameters (and, for a
host-to-camera data phase, the same data), in recorded order; only the
transaction id is rewritten to the host's. A command the real camera never
received raises :class:`ReplayMismatch` naming it and what the recording holds
for that operation, and is kept in :attr:`ReplayCamera.unrecorded`.

Log formats read
----------------
* the plain log as written by ``gphoto2 --debug --debug-logfile=FILE`` (any
  language: only the ``Writing N=0x.. bytes``, ``Reading N=0x.. bytes`` /
  ``Could only read N``, ``Hexdump of N = 0x.. bytes follows:`` markers and the
  hex rows ``OFFSET  xx xx .. xx-xx .. xx  ASCII`` are used);
* the same log copied out of a web paste page: every line prefixed with its
  number (``  123. ``), long lines wrapped onto unnumbered continuation lines,
  and link markers such as ``[17]`` inserted into the text.

Several gphoto2 runs may follow each other in one file (the timestamps restart);
a run must not end inside a container. A dump is attributed to the host
(``Writing``) or the camera (``Reading``/``Could only read``) by the last such
line before it. Bytes of one direction are concatenated and cut into
containers by their length field, so a container read in several transfers
(e.g. 512 bytes, then 6656, then the rest) is reassembled.

Adding a recording: save the complete debug log (do not trim hex dumps), load
it with :func:`load_recording` (a malformed log raises :class:`RecordingError`
naming the file, the line and what was wrong) and check
:attr:`Recording.transactions`.
"""

from __future__ import annotations

import errno
import re
import struct
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import usb.backend
import usb.core

from pipeline.errors import InputError, TetherError
from pipeline.tether.clock import VirtualClock
from pipeline.tether.codes import (
    OC,
    RC,
    USB_VENDOR_IDS,
    ClassRequest,
    ContainerType,
    operation_name,
    response_name,
)
from pipeline.tether.host_backend import TIMEOUT, HostBackend
from pipeline.tether.ptp import HEADER, DeviceInfo, ProtocolError

__all__ = [
    "RecordedTransaction",
    "Recording",
    "RecordingError",
    "ReplayBackend",
    "ReplayCamera",
    "ReplayMismatch",
    "load_recording",
    "parse_hexdumps",
]

_EPIPE = (-9, errno.EPIPE)  # LIBUSB_ERROR_PIPE
_ROW_BYTES = 16


class RecordingError(InputError):
    """A recorded log that cannot be parsed; the message names the file and line."""


class ReplayMismatch(TetherError):
    """The host sent a command (or data) that the recorded camera never received."""


# --- log text -> logical lines ------------------------------------------------------------

_NUMBERED = re.compile(r"^\s*(\d+)\.(?:\s(.*))?$")
_NUMBERED_LOG_LINE = re.compile(r"^\s*\d+\.\s+\d+\.\d+\s")
_LINK_MARKER = re.compile(r"\[\d+\]")
_TIMESTAMP = re.compile(r"^(\d+\.\d+)\s")
_WRITE = re.compile(r"\bWriting (\d+)=0x([0-9a-fA-F]+) byte")
_READ = re.compile(r"\b(?:Reading (\d+)=0x[0-9a-fA-F]+ byte|Could only read (\d+) out of)")
_HEXDUMP = re.compile(r"\bHexdump of (\d+) = 0x([0-9a-fA-F]+) bytes? follows")
_ROW = re.compile(r"^([0-9a-fA-F]{4,8}) +(\S.*)?$")
_HEX_BYTE = re.compile(r"^[0-9a-fA-F]{2}$")
_USB_IDS = re.compile(r"vendor 0x([0-9a-fA-F]+), product 0x([0-9a-fA-F]+)\)\.\.\. found")
_ENDPOINTS = re.compile(r"inep ([0-9a-fA-F]+), outep ([0-9a-fA-F]+), intep ([0-9a-fA-F]+)")
_PACKET = re.compile(r"maxpacketsize (\d+)")


@dataclass(frozen=True)
class _Line:
    number: int  # 1-based line number in the file where this logical line starts
    text: str


def _logical_lines(text: str) -> list[_Line]:
    """Lines of a plain log, or the joined numbered lines of a log copied from a paste page."""
    physical = text.splitlines()
    listing = sum(1 for line in physical[:5000] if _NUMBERED_LOG_LINE.match(line)) >= 3
    if not listing:
        return [_Line(i, line.rstrip()) for i, line in enumerate(physical, 1)]
    lines: list[_Line] = []
    for i, line in enumerate(physical, 1):
        numbered = _NUMBERED.match(line)
        if numbered:
            lines.append(_Line(i, _LINK_MARKER.sub("", numbered.group(2) or "").rstrip()))
        elif lines and line.strip():  # continuation of a wrapped line
            joined = lines[-1].text + " " + _LINK_MARKER.sub("", line.strip())
            lines[-1] = _Line(lines[-1].number, joined)
    return lines


# --- logical lines -> hex-dumped transfers ------------------------------------------------


@dataclass(frozen=True)
class Transfer:
    """The bytes of one hex dump: ``"out"`` (host to camera) or ``"in"``, and where it is."""

    direction: str
    data: bytes
    line: int
    run: int  # index of the gphoto2 run in the file (timestamps restart between runs)


def _row_bytes(line: _Line, expected_offset: int, count: int, where: str) -> bytes:
    match = _ROW.match(line.text)
    if not match:
        raise RecordingError(
            f"{where}:{line.number}: expected a hex dump row at offset 0x{expected_offset:04x}, "
            f"got {line.text[:60]!r} (the dump is cut short)"
        )
    offset = int(match.group(1), 16)
    if offset != expected_offset:
        raise RecordingError(
            f"{where}:{line.number}: hex dump row offset 0x{offset:04x}, expected "
            f"0x{expected_offset:04x} (rows missing or out of order)"
        )
    tokens: list[str] = []  # the bytes; the "-" after the 8th byte and the ASCII column follow
    for word in (match.group(2) or "").split():
        tokens += [part for part in word.split("-") if part]
        if len(tokens) >= count:
            break
    tokens = tokens[:count]
    bad = [t for t in tokens if not _HEX_BYTE.match(t)]
    if len(tokens) < count or bad:
        raise RecordingError(
            f"{where}:{line.number}: hex dump row at 0x{offset:04x} should hold {count} bytes, "
            f"found {len(tokens) - len(bad)} hex bytes"
            + (f" and {bad[0]!r}" if bad else "")
        )
    return bytes(int(t, 16) for t in tokens)


def parse_hexdumps(path: str | Path) -> list[Transfer]:
    """Every hex-dumped USB transfer of a ``gphoto2 --debug`` log, in order.

    Parameters
    ----------
    path : str or Path
        The log (plain, or copied from a numbered paste page; see the module docstring).

    Returns
    -------
    list of Transfer
        One per ``Hexdump of N = 0x.. bytes follows:`` block, with its direction
        taken from the last ``Writing`` / ``Reading`` line before it.

    Raises
    ------
    RecordingError
        The file cannot be read, holds no hex dump, or a dump is malformed:
        its two byte counts differ, a row is missing, short or out of order, or
        no ``Writing``/``Reading`` line tells its direction.
    """
    path = Path(path)
    return _hexdumps(_read_lines(path), path)


def _read_lines(path: Path) -> list[_Line]:
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise RecordingError(f"{path}: cannot read the recording: {err.strerror or err}") from err
    return _logical_lines(text)


def _hexdumps(lines: list[_Line], path: Path) -> list[Transfer]:
    transfers: list[Transfer] = []
    direction: str | None = None
    run, last_time = 0, -1.0
    i = 0
    while i < len(lines):
        line = lines[i]
        i += 1
        stamp = _TIMESTAMP.match(line.text)
        if stamp:
            now = float(stamp.group(1))
            if now < last_time:
                run += 1
                direction = None
            last_time = now
        if _WRITE.search(line.text):
            direction = "out"
            continue
        if _READ.search(line.text):
            direction = "in"
            continue
        dump = _HEXDUMP.search(line.text)
        if not dump:
            continue
        count, count_hex = int(dump.group(1)), int(dump.group(2), 16)
        if count != count_hex:
            raise RecordingError(
                f"{path}:{line.number}: hex dump header says {count} = 0x{count_hex:x} bytes"
            )
        if direction is None:
            raise RecordingError(
                f"{path}:{line.number}: hex dump with no 'Writing'/'Reading' line before it "
                "(cannot tell whether the host or the camera sent it)"
            )
        data = bytearray()
        while len(data) < count:
            if i >= len(lines):
                raise RecordingError(
                    f"{path}:{line.number}: hex dump of {count} bytes ends after {len(data)} "
                    "bytes at the end of the file"
                )
            data += _row_bytes(lines[i], len(data), min(_ROW_BYTES, count - len(data)), str(path))
            i += 1
        transfers.append(Transfer(direction, bytes(data), line.number, run))
        direction = None
    if not transfers:
        raise RecordingError(
            f"{path}: no 'Hexdump of N = 0x.. bytes follows:' blocks: not a gphoto2 --debug log "
            "(or it was recorded without hex dumps)"
        )
    return transfers


# --- transfers -> containers -> transactions ----------------------------------------------


@dataclass(frozen=True)
class _Container:
    direction: str
    type: int
    code: int
    tid: int
    body: bytes
    line: int
    run: int

    @property
    def params(self) -> tuple[int, ...]:
        return struct.unpack(f"<{len(self.body) // 4}I", self.body[: len(self.body) // 4 * 4])


def _containers(transfers: list[Transfer], where: Path) -> list[_Container]:
    """Cut each direction's byte stream into containers, in the order they completed."""
    out: list[_Container] = []
    pending = {"out": bytearray(), "in": bytearray()}
    started = {"out": 0, "in": 0}
    run = 0
    for t in transfers:
        if t.run != run:
            _check_empty(pending, started, where, "the gphoto2 run ends")
            run = t.run
        buf = pending[t.direction]
        if not buf:
            started[t.direction] = t.line
        buf += t.data
        while len(buf) >= HEADER.size:
            length, ctype, code, tid = HEADER.unpack_from(buf)
            if length < HEADER.size or ctype not in ContainerType._value2member_map_:
                who = "host" if t.direction == "out" else "camera"
                raise RecordingError(
                    f"{where}:{started[t.direction]}: bytes sent by the {who} do not start a PTP "
                    f"container (length {length}, type {ctype}; expected type 1-4)"
                )
            if len(buf) < length:
                break
            out.append(_Container(t.direction, ctype, code, tid, bytes(buf[HEADER.size:length]),
                                  started[t.direction], t.run))
            del buf[:length]
            started[t.direction] = t.line
    _check_empty(pending, started, where, "the file ends")
    return out


def _check_empty(pending: dict, started: dict, where: Path, when: str) -> None:
    for direction, buf in pending.items():
        if buf:
            length = HEADER.unpack_from(buf)[0] if len(buf) >= HEADER.size else None
            raise RecordingError(
                f"{where}:{started[direction]}: {when} inside a container "
                f"({len(buf)} of {length if length is not None else '?'} bytes recorded)"
            )


@dataclass(frozen=True)
class RecordedTransaction:
    """One recorded PTP transaction.

    Attributes
    ----------
    code, params : int, tuple of int
        The command's operation code and parameters.
    data_out : bytes or None
        Payload of a host-to-camera data phase (None if there was none).
    data_in : bytes or None
        Payload of a camera-to-host data phase (None if there was none).
    response_code : int or None
        The camera's response code; None if the log ends before the response.
    response_params : tuple of int
    line : int
        Line of the command's hex dump in the log.
    run : int
        Index of the gphoto2 run in the log.
    """

    code: int
    params: tuple[int, ...]
    data_out: bytes | None
    data_in: bytes | None
    response_code: int | None
    response_params: tuple[int, ...]
    line: int
    run: int

    def describe(self, vendor: str | None = None) -> str:
        """``"GetEvent (0x9116)() -> OK (0x2001), line 123"``-style summary."""
        params = ", ".join(f"0x{p:x}" for p in self.params)
        data = f" + {len(self.data_out)} data bytes" if self.data_out is not None else ""
        answer = ("no response" if self.response_code is None
                  else response_name(self.response_code, vendor))
        return f"{operation_name(self.code, vendor)}({params}){data} -> {answer}, line {self.line}"


def _transactions(containers: list[_Container], where: Path) -> list[RecordedTransaction]:
    result: list[RecordedTransaction] = []
    command: _Container | None = None
    data_out = data_in = None

    def finish(response: _Container | None) -> None:
        result.append(RecordedTransaction(
            command.code, command.params, data_out, data_in,
            response.code if response else None, response.params if response else (),
            command.line, command.run,
        ))

    for c in containers:
        if c.type == ContainerType.EVENT:
            continue  # events on bulk-in are not part of a transaction
        if c.type == ContainerType.COMMAND:
            if c.direction != "out":
                raise RecordingError(f"{where}:{c.line}: the camera sent a command container")
            if command is not None:
                finish(None)  # the previous command was never answered
            command, data_out, data_in = c, None, None
            if len(c.body) % 4 or len(c.body) > 20:
                raise RecordingError(
                    f"{where}:{c.line}: command 0x{c.code:04x} has {len(c.body)} parameter bytes"
                )
            continue
        if command is None or c.tid != command.tid or c.run != command.run:
            raise RecordingError(
                f"{where}:{c.line}: {ContainerType(c.type).name.lower()} container for "
                f"transaction {c.tid} without a command of that transaction before it"
            )
        if c.type == ContainerType.DATA:
            if c.direction == "out":
                data_out = c.body
            else:
                data_in = c.body
            continue
        if c.direction != "in":
            raise RecordingError(f"{where}:{c.line}: the host sent a response container")
        finish(c)
        command = None
    if command is not None:
        finish(None)
    return result


@dataclass(frozen=True)
class Recording:
    """A parsed recording: its transactions and the USB identity of the recorded camera.

    Attributes
    ----------
    path : Path
    transactions : tuple of RecordedTransaction
        In recorded order, all runs of the log.
    id_vendor, id_product : int or None
        USB ids found in the log (``Looking for USB device (vendor .., product ..)... found``).
    packet_size : int
        Bulk endpoint packet size (``maxpacketsize``; 512 if not in the log).
    endpoints : tuple of int
        Bulk-in, bulk-out and interrupt endpoint addresses.
    """

    path: Path
    transactions: tuple[RecordedTransaction, ...]
    id_vendor: int | None = None
    id_product: int | None = None
    packet_size: int = 512
    endpoints: tuple[int, int, int] = (0x81, 0x02, 0x83)

    @property
    def device_info(self) -> DeviceInfo | None:
        """The first recorded GetDeviceInfo dataset, parsed by the project's codec."""
        for t in self.transactions:
            if t.code == OC.GetDeviceInfo and t.data_in is not None:
                return DeviceInfo.from_bytes(t.data_in)
        return None

    def with_code(self, code: int) -> list[RecordedTransaction]:
        """The recorded transactions of one operation code."""
        return [t for t in self.transactions if t.code == code]


def load_recording(path: str | Path) -> Recording:
    """Parse a ``gphoto2 --debug`` log into a :class:`Recording`.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Recording

    Raises
    ------
    RecordingError
        Malformed hex dumps (see :func:`parse_hexdumps`), bytes that are not PTP
        containers, a data or response container without its command, or a run
        that ends inside a container; the message names the file and line.
    """
    path = Path(path)
    lines = _read_lines(path)
    transactions = _transactions(_containers(_hexdumps(lines, path), path), path)
    text = "\n".join(line.text for line in lines)
    ids = _USB_IDS.search(text)
    eps = _ENDPOINTS.search(text)
    packet = _PACKET.search(text)
    return Recording(
        path=path,
        transactions=tuple(transactions),
        id_vendor=int(ids.group(1), 16) if ids else None,
        id_product=int(ids.group(2), 16) if ids else None,
        packet_size=int(packet.group(1)) if packet else 512,
        endpoints=tuple(int(g, 16) for g in eps.groups()) if eps else (0x81, 0x02, 0x83),
    )


# --- the replaying device -----------------------------------------------------------------


@dataclass(frozen=True)
class Unrecorded:
    """A command (with its host data phase, if any) that the recording never saw."""

    code: int
    params: tuple[int, ...]
    data_out: bytes | None

    def describe(self, vendor: str | None = None) -> str:
        """``"SetRemoteMode (0x9114)(0x2)"``, with the data phase in hex if there was one."""
        params = ", ".join(f"0x{p:x}" for p in self.params)
        data = f" + data {self.data_out.hex()}" if self.data_out is not None else ""
        return f"{operation_name(self.code, vendor)}({params}){data}"


@dataclass
class ReplayCamera:
    """The device side of a replay: answers commands from a :class:`Recording`.

    Parameters
    ----------
    recording : Recording
    on_exhausted : {"error", "repeat-last"}
        When the host sends a command more often than it was recorded:
        ``"error"`` raises :class:`ReplayMismatch`; ``"repeat-last"`` answers
        with the last recorded transaction again (a camera that stays busy).
    id_vendor, id_product : int, optional
        USB ids; default: those in the log, else the manufacturer's vendor id.

    Attributes
    ----------
    served : list of RecordedTransaction
        The recorded transactions played back, in the order they were served.
    unrecorded : list of Unrecorded
        Commands the recorded camera never received (each also raised).
    """

    recording: Recording
    on_exhausted: str = "error"
    id_vendor: int | None = None
    id_product: int | None = None
    bus: int = 1
    address: int = 7
    served: list[RecordedTransaction] = field(default_factory=list)
    unrecorded: list[Unrecorded] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.on_exhausted not in ("error", "repeat-last"):
            raise ValueError(f"on_exhausted must be 'error' or 'repeat-last', "
                             f"got {self.on_exhausted!r}")
        rec = self.recording
        info = rec.device_info
        self.strings = {1: info.manufacturer if info else "", 2: info.model if info else "",
                        3: info.serial_number if info else ""}
        if self.id_vendor is None:
            maker = self.strings[1].lower()
            guess = next((vid for vid, name in USB_VENDOR_IDS.items() if name in maker), 0)
            self.id_vendor = rec.id_vendor if rec.id_vendor is not None else guess
        if self.id_product is None:
            self.id_product = rec.id_product or 0
        self.vendor = USB_VENDOR_IDS.get(self.id_vendor)
        self.packet_size = rec.packet_size
        self._queues: dict[tuple, deque[RecordedTransaction]] = {}
        self._last: dict[tuple, RecordedTransaction] = {}
        self._data_out_ops = set()
        for t in rec.transactions:
            if t.response_code is None:
                continue  # never answered: nothing to play back
            self._queues.setdefault(self._key(t.code, t.params, t.data_out), deque()).append(t)
            if t.data_out is not None:
                self._data_out_ops.add(t.code)
        self._in = bytearray()
        self._command: tuple[int, int, tuple[int, ...]] | None = None  # code, tid, params
        self._expect_zlp = False
        self._out: list[bytes] = []
        self._out_pos = 0
        self._zlp_due = False

    @staticmethod
    def _key(code: int, params: tuple[int, ...], data_out: bytes | None) -> tuple:
        return code, tuple(params), data_out

    def remaining(self, code: int | None = None) -> int:
        """How many recorded transactions (of one operation code) are still unplayed."""
        return sum(len(q) for key, q in self._queues.items() if code is None or key[0] == code)

    # --- bulk out -----------------------------------------------------------------------

    def host_write(self, data: bytes) -> int:
        """Bulk-out: collect containers; answer a command (after its data phase, if recorded)."""
        if not data:
            self._expect_zlp = False  # the zero-length packet after a full-packet container
            return 0
        self._in += data
        while len(self._in) >= HEADER.size:
            length, ctype, code, tid = HEADER.unpack_from(self._in)
            if length < HEADER.size or ctype not in ContainerType._value2member_map_:
                raise ProtocolError(f"replay: the host wrote a malformed container header "
                                    f"(length {length}, type {ctype})")
            if len(self._in) < length:
                break
            blob, self._in = bytes(self._in[:length]), self._in[length:]
            self._container_in(ctype, code, tid, blob[HEADER.size:])
        return len(data)

    def _container_in(self, ctype: int, code: int, tid: int, body: bytes) -> None:
        if ctype == ContainerType.COMMAND:
            params = struct.unpack(f"<{len(body) // 4}I", body[: len(body) // 4 * 4])
            self._command = (code, tid, params)
            if code not in self._data_out_ops:
                self._answer(None)
        elif ctype == ContainerType.DATA and self._command is not None:
            self._answer(body)
        else:
            raise ProtocolError(f"replay: unexpected {ContainerType(ctype).name} container "
                                f"0x{code:04x} from the host")

    def _answer(self, data_out: bytes | None) -> None:
        code, tid, params = self._command
        self._command = None
        key = self._key(code, params, data_out)
        queue = self._queues.get(key)
        if queue:
            t = queue.popleft()
            self._last[key] = t
        elif key in self._last and self.on_exhausted == "repeat-last":
            t = self._last[key]
        else:
            miss = Unrecorded(code, params, data_out)
            self.unrecorded.append(miss)
            raise ReplayMismatch(self._mismatch_message(miss, key in self._last))
        self.served.append(t)
        if t.data_in is not None:
            self._out.append(HEADER.pack(HEADER.size + len(t.data_in), ContainerType.DATA, code,
                                         tid) + t.data_in)
        params_out = b"".join(struct.pack("<I", p) for p in t.response_params)
        self._out.append(HEADER.pack(HEADER.size + len(params_out), ContainerType.RESPONSE,
                                     t.response_code, tid) + params_out)

    def _mismatch_message(self, miss: Unrecorded, used_up: bool) -> str:
        where = self.recording.path.name
        if used_up:
            count = sum(1 for t in self.served if self._key(t.code, t.params, t.data_out)
                        == self._key(miss.code, miss.params, miss.data_out))
            return (f"{miss.describe(self.vendor)} was recorded only {count} time(s) in {where}; "
                    "all were played back")
        same_op = [t for t in self.recording.transactions if t.code == miss.code]
        if not same_op:
            return (f"{miss.describe(self.vendor)}: the camera in {where} never received "
                    f"{operation_name(miss.code, self.vendor)}")
        variants = sorted({
            "(" + ", ".join(f"0x{p:x}" for p in t.params) + ")"
            + (f" + data {t.data_out.hex()}" if t.data_out is not None else "")
            for t in same_op
        })
        shown = "; ".join(variants[:8]) + (f"; ... ({len(variants)} in all)"
                                           if len(variants) > 8 else "")
        return (f"{miss.describe(self.vendor)}: the camera in {where} never received these "
                f"parameters/data; recorded: {shown}")

    # --- bulk in ------------------------------------------------------------------------

    def host_read(self, size: int) -> bytes:
        """Bulk-in: the queued data/response containers, then a zero-length packet if due."""
        if not (self._out or self._zlp_due):
            raise usb.core.USBTimeoutError("Operation timed out", *TIMEOUT)
        if not self._out:
            self._zlp_due = False
            return b""
        current = self._out[0]
        n = min(size, len(current) - self._out_pos)
        chunk = current[self._out_pos:self._out_pos + n]
        self._out_pos += n
        if self._out_pos == len(current):
            self._out.pop(0)
            self._out_pos = 0
            self._zlp_due = len(current) % self.packet_size == 0 and n == size
        return chunk

    # --- class requests -----------------------------------------------------------------

    def class_request(self, request: int, data: bytes | None) -> bytes | int:
        """Still Image class requests: cancel and reset drop queued answers; status is OK."""
        if request in (ClassRequest.CANCEL, ClassRequest.DEVICE_RESET):
            self._out, self._out_pos, self._zlp_due, self._command = [], 0, False, None
            return len(data or b"")
        if request == ClassRequest.GET_DEVICE_STATUS:
            return struct.pack("<HH", 4, RC.OK)
        raise usb.core.USBError("Pipe error", *_EPIPE)

    def check_all_recorded(self) -> None:
        """Raise :class:`ReplayMismatch` listing every command the recording did not hold."""
        if self.unrecorded:
            listing = "; ".join(m.describe(self.vendor) for m in self.unrecorded)
            raise ReplayMismatch(
                f"{len(self.unrecorded)} command(s) never received by the camera in "
                f"{self.recording.path.name}: {listing}"
            )


class ReplayBackend(HostBackend):
    """A pyusb backend with one :class:`ReplayCamera`.

    Parameters
    ----------
    camera : ReplayCamera or Recording or path
        A recording (or the path of a log) is wrapped in a :class:`ReplayCamera`
        with default options.
    clock : optional
        The clock a session over this backend should use (``backend.clock``, as
        :func:`pipeline.tether.flows.connect` looks it up). Default: a
        :class:`~pipeline.tether.clock.VirtualClock`: a recording answers at once,
        so the host's retry and pacing waits cost no real time.

    Examples
    --------
    >>> backend = ReplayBackend("canon-eos-60d.debug.log")  # doctest: +SKIP
    >>> device = usb.core.find(backend=backend)  # doctest: +SKIP
    >>> session = PtpSession(UsbTransport(device), clock=backend.clock)  # doctest: +SKIP
    """

    def __init__(self, camera, *, clock=None) -> None:
        super().__init__()
        self.clock = VirtualClock() if clock is None else clock
        if isinstance(camera, (str, Path)):
            camera = load_recording(camera)
        if isinstance(camera, Recording):
            camera = ReplayCamera(camera)
        self.camera = camera

    def enumerate_devices(self):
        return [self.camera]

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=dev.id_vendor,
            idProduct=dev.id_product, bcdDevice=0x0100, iManufacturer=1, iProduct=2,
            iSerialNumber=3, bNumConfigurations=1, bus=dev.bus, address=dev.address,
            port_number=1, port_numbers=(1,), speed=3,
        )

    def endpoints(self, dev):
        bulk_in, bulk_out, intr = dev.recording.endpoints
        return ((bulk_in, 2, dev.packet_size), (bulk_out, 2, dev.packet_size), (intr, 3, 8))

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        if bmRequestType & 0x60 == 0x20:  # class request to the interface
            length = len(data) * data.itemsize if data is not None else 0
            out = None if bmRequestType & 0x80 else bytes(data or b"")
            result = dev_handle.class_request(bRequest, out)
            if isinstance(result, int):
                return result
            data[: min(len(result), length)] = type(data)(data.typecode, result[:length])
            return min(len(result), length)
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR string
            index = wValue & 0xFF
            payload = (struct.pack("<H", 0x0409) if index == 0
                       else dev_handle.strings.get(index, "").encode("utf-16-le"))
            blob = bytes([2 + len(payload), 3]) + payload
            data[: min(len(blob), len(data))] = type(data)(data.typecode, blob[: len(data)])
            return min(len(blob), len(data))
        raise usb.core.USBError("Pipe error", *_EPIPE)

    def clear_halt(self, dev_handle, ep):
        return None

    def reset_device(self, dev_handle):
        return None


def main(argv: list[str] | None = None) -> int:
    """``python -m pipeline.tether.replay LOG``: list the transactions of a recording.

    Use it to check a new recording before writing tests against it; a
    malformed log prints the one-line :class:`RecordingError` and returns 1.
    """
    import sys

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m pipeline.tether.replay GPHOTO2_DEBUG_LOG", file=sys.stderr)
        return 2
    try:
        rec = load_recording(args[0])
    except RecordingError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    info = rec.device_info
    vendor = USB_VENDOR_IDS.get(rec.id_vendor or 0)
    ids = (f"{rec.id_vendor:04x}:{rec.id_product:04x}" if rec.id_vendor is not None
           else "USB ids not in the log")
    print(f"{rec.path.name}: {info.model if info else 'no GetDeviceInfo'} ({ids}), "
          f"{len(rec.transactions)} transactions in {1 + max(t.run for t in rec.transactions)} "
          "run(s)")
    for t in rec.transactions:
        phases = "".join(f" [{label} {len(blob)} B]" for label, blob in
                         (("out", t.data_out), ("in", t.data_in)) if blob is not None)
        print(f"  run {t.run}: {t.describe(vendor)}{phases}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
