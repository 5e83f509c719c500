"""Canon EOS: remote mode, event polling, EVF live view, DriveLens, remote release.

Sequence as in libgphoto2's ``camlibs/ptp2/library.c`` / ``config.c``:
SetRemoteMode(1), SetEventMode(1), EVFOutputDevice = PC (live view, required
before DriveLens), DriveLens(0x0001-0x0003 near, 0x8001-0x8003 far),
RemoteReleaseOn/Off (full press), GetEvent until ObjectAddedEx, then
GetPartialObject in chunks and TransferComplete.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from pipeline.errors import InputError
from pipeline.tether.camera import CapturedObject, DriveRefused, FocusCamera
from pipeline.tether.codes import (
    CANON_DRIVE_FAR,
    CANON_EVF_OFF,
    CANON_EVF_PC,
    CanonDPC,
    CanonEC,
    CanonOC,
    CanonRC,
)
from pipeline.tether.ptp import ProtocolError
from pipeline.tether.session import PtpError

RELEASE_FULL = 3  # RemoteReleaseOn/Off first parameter: 1 half press, 2 full, 3 both
RELEASE_AF = 0  # second parameter of RemoteReleaseOn


@dataclass(frozen=True)
class CanonEvent:
    """One record of EOS GetEvent data: its type and the u32 words that follow."""

    type: int
    words: tuple[int, ...]
    raw: bytes

    @property
    def filename(self) -> str:
        """ObjectAddedEx: the file name at byte 0x28 of the record."""
        return self.raw[0x28:].split(b"\x00", 1)[0].decode("ascii", "replace")


def parse_events(data: bytes) -> list[CanonEvent]:
    """Records ``u32 size, u32 type, payload`` up to the terminator (type 0, size 8)."""
    events, pos = [], 0
    while pos + 8 <= len(data):
        size, kind = struct.unpack_from("<II", data, pos)
        if kind == 0:
            break
        if size < 8 or pos + size > len(data):
            raise ProtocolError(f"EOS GetEvent record at byte {pos} has size {size}")
        raw = data[pos : pos + size]
        words = struct.unpack_from(f"<{(size - 8) // 4}I", raw, 8)
        events.append(CanonEvent(kind, words, raw))
        pos += size
    return events


def encode_event(kind: int, words: tuple[int, ...] = (), tail: bytes = b"") -> bytes:
    """One EOS event record (the inverse of :func:`parse_events`, for the emulator)."""
    body = struct.pack(f"<{len(words)}I", *words) + tail
    return struct.pack("<II", 8 + len(body), kind) + body


EVENT_TERMINATOR = struct.pack("<II", 8, 0)


class CanonEOS(FocusCamera):
    vendor = "canon"
    stack_ops = (
        CanonOC.SetRemoteMode, CanonOC.SetEventMode, CanonOC.GetEvent,
        CanonOC.SetDevicePropValueEx, CanonOC.DriveLens, CanonOC.RemoteReleaseOn,
        CanonOC.RemoteReleaseOff, CanonOC.GetPartialObject, CanonOC.TransferComplete,
    )
    bulb_ops = stack_ops
    refusal_codes = (CanonRC.OperationRefused,)

    def __post_init__(self) -> None:
        if self.drive_size not in (1, 2, 3):
            raise InputError(f"Canon DriveLens step size must be 1, 2 or 3, got {self.drive_size}")
        self.session.busy_codes |= {CanonRC.ObjectNotReady, CanonRC.MemoryStatusNotReady}
        self.status = 0
        self.properties: dict[int, int] = {}
        self._objects: list[CapturedObject] = []

    def start(self) -> None:
        s = self.session
        s.transaction(CanonOC.SetRemoteMode, (1,))
        s.transaction(CanonOC.SetEventMode, (1,))
        self.poll_events()
        self.set_property(CanonDPC.EVFOutputDevice, CANON_EVF_PC)
        self._poll("live view (EVF output to PC)", self._evf_on)

    def _evf_on(self):
        self.poll_events()
        return True if self.properties.get(CanonDPC.EVFOutputDevice) == CANON_EVF_PC else None

    def set_property(self, prop: int, value: int) -> None:
        """SetDevicePropValueEx: data ``u32 size (12), u32 property, u32 value``."""
        data = struct.pack("<III", 12, prop, value)
        self.session.transaction(CanonOC.SetDevicePropValueEx, data_out=data)

    def poll_events(self) -> list[CanonEvent]:
        """GetEvent; remembers property values, camera status and new objects."""
        data = self.session.transaction(CanonOC.GetEvent, want_data=True).data
        events = parse_events(data)
        for ev in events:
            if ev.type == CanonEC.PropValueChanged and len(ev.words) >= 2:
                self.properties[ev.words[0]] = ev.words[1]
            elif ev.type == CanonEC.CameraStatusChanged and ev.words:
                self.status = ev.words[0]
            elif ev.type == CanonEC.ObjectAddedEx and len(ev.words) >= 6:
                self._objects.append(CapturedObject(ev.words[0], ev.words[5], ev.filename))
        return events

    def _drive(self, steps: int) -> None:
        code = self.drive_size | (CANON_DRIVE_FAR if steps > 0 else 0)
        for _ in range(abs(steps)):
            try:
                self.session.transaction(CanonOC.DriveLens, (code,))
            except PtpError as err:
                if err.code in self.refusal_codes:
                    raise DriveRefused(str(err), err.code) from err
                raise

    def capture(self) -> CapturedObject:
        self.open_exposure()
        return self.close_exposure()

    def open_exposure(self) -> None:
        self._objects.clear()
        self.session.transaction(CanonOC.RemoteReleaseOn, (RELEASE_FULL, RELEASE_AF))

    def close_exposure(self) -> CapturedObject:
        self.session.transaction(CanonOC.RemoteReleaseOff, (RELEASE_FULL,))
        return self._poll("waiting for the captured image (ObjectAddedEx)", self._next_object)

    def _next_object(self) -> CapturedObject | None:
        if not self._objects:
            self.poll_events()
        return self._objects.pop(0) if self._objects else None

    def _partial(self, obj: CapturedObject, offset: int, length: int) -> bytes:
        return self.session.transaction(
            CanonOC.GetPartialObject, (obj.handle, offset, length), want_data=True
        ).data

    def _download_done(self, obj: CapturedObject) -> None:
        self.session.transaction(CanonOC.TransferComplete, (obj.handle,))

    def safe_state(self) -> None:
        self._quietly("turn live view off", self.set_property, CanonDPC.EVFOutputDevice,
                      CANON_EVF_OFF)
        self._quietly("leave event mode", self.session.transaction, CanonOC.SetEventMode, (0,))
        self._quietly("leave remote mode", self.session.transaction, CanonOC.SetRemoteMode, (0,))


def object_added_record(handle: int, size: int, filename: str) -> bytes:
    """An ObjectAddedEx record: handle @8, storage @0x0C, format @0x10, size @0x1C, name @0x28."""
    words = (handle, 0x00010001, 0x3801, 0, 0, size, 0, 0)
    return encode_event(CanonEC.ObjectAddedEx, words, filename.encode("ascii") + b"\x00")
