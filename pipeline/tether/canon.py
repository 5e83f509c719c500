"""Canon EOS: remote mode, event polling, EVF live view, DriveLens, the MF remote release.

The order of operations follows libgphoto2 (``camlibs/ptp2/library.c``,
``config.c``), written from its documented behaviour:

* start: SetRemoteMode (1; EOS M bodies 0x15), SetEventMode(1), GetEvent (the
  property dump: FocusMode 0xD108, CaptureDestination 0xD11C, ...), refuse a
  lens switched to MF (DriveLens would silently do nothing), EVFMode (0xD1B1) = 1,
  EVFOutputDevice (0xD1B0) = PC, GetEvent until live view is reported on;
* drive: DriveLens (0x0001-0x0003 near, 0x8001-0x8003 far), one GetEvent after
  each, commands paced so that none arrives while the motor still runs (bodies
  drop or refuse those);
* capture: GetEvent until empty (else the release answers busy), then
  RemoteReleaseOn(3 = full press, 1 = no AF) and RemoteReleaseOff(3): the AF
  release (second parameter 0) would refocus and undo the drive;
* events: PropValueChanged (0xC189) records carry ``u32 property`` and a value
  whose length is the record's: 1, 2 or 4 bytes for numbers, and strings (serial
  number, lens name, owner) or arrays of up to dozens of bytes; every value is
  kept whole (:attr:`CanonEOS.property_bytes`) and decoded by its length;
* new image: ObjectAddedEx (0xC181) or ObjectAddedEx64 (0xC1A7, EOS R era) for
  an image on the card; RequestObjectTransfer (0xC186) for one held in RAM
  (CaptureDestination = PC), which is released with TransferComplete after the
  download; folder objects (format 0x3001) are skipped.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass

from pipeline.errors import InputError
from pipeline.tether.base import CapturedObject, DriveRefused, FocusCamera, LensAtManual
from pipeline.tether.codes import (
    CANON_DRIVE_FAR,
    CANON_EVF_OFF,
    CANON_EVF_PC,
    CANON_FOCUS_MODE_MF,
    CANON_REMOTE_MODE,
    CANON_REMOTE_MODE_EOS_M,
    CANON_STRING_PROPERTIES,
    OBJECT_FORMAT_ASSOCIATION,
    CanonDPC,
    CanonEC,
    CanonOC,
    CanonRC,
)
from pipeline.tether.ptp import ProtocolError
from pipeline.tether.session import PtpError

log = logging.getLogger(__name__)

RELEASE_FULL = 3  # RemoteReleaseOn/Off first parameter: 1 half press, 2 full, 3 both
RELEASE_NO_AF = 1  # RemoteReleaseOn second parameter: 0 = AF before the shot, 1 = MF (no AF)
DRIVE_PACE_S = {1: 0.1, 2: 0.2, 3: 0.4}  # least time between DriveLens commands, per size
MAX_DRAIN = 50  # GetEvent calls that may still return records before a capture


@dataclass(frozen=True)
class CanonEvent:
    """One record of EOS GetEvent data: its type and the u32 words that follow."""

    type: int
    words: tuple[int, ...]
    raw: bytes

    def u16(self, offset: int) -> int:
        return struct.unpack_from("<H", self.raw, offset)[0] if offset + 2 <= len(self.raw) else 0

    def u32(self, offset: int) -> int:
        return struct.unpack_from("<I", self.raw, offset)[0] if offset + 4 <= len(self.raw) else 0

    def text(self, offset: int) -> str:
        return self.raw[offset:].split(b"\x00", 1)[0].decode("ascii", "replace")

    @property
    def filename(self) -> str:
        """ObjectAddedEx: the file name at byte 0x28 of the record."""
        return self.text(0x28)


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


def property_value(prop: int, raw: bytes) -> int | str | bytes:
    """A PropValueChanged value, decoded by its length.

    1, 2 or 4 bytes: an unsigned little-endian integer (the 60D sends a 1-byte
    record ``0d000000 89c10000 15d10000 00`` for 0xD115); a longer value of a
    string property (:data:`~pipeline.tether.codes.CANON_STRING_PROPERTIES`) is
    its text up to the first NUL; any other value stays bytes (an array). A
    string property may also arrive as 1-4 bytes (an empty Owner 0xD115 is the
    single NUL byte) and is then an integer here: :meth:`CanonEOS.property_text`
    reads any value as text.
    """
    if len(raw) in (1, 2, 4):
        return int.from_bytes(raw, "little")
    if prop in CANON_STRING_PROPERTIES:
        return _text(raw)
    return raw


def _text(raw: bytes) -> str:
    return raw.split(b"\x00", 1)[0].decode("ascii", "replace")


def object_of(ev: CanonEvent) -> tuple[CapturedObject, int] | None:
    """The object a new-image record announces, with its format; None for other records.

    Offsets (libgphoto2 ``ptp-pack.c``): ObjectAddedEx handle 0x08, format 0x10,
    size 0x1C, name 0x28; ObjectAddedEx64 the same but name 0x2C (and a 64-bit
    size); RequestObjectTransfer handle 0x08, format 0x0C, size 0x14, name 0x1C.
    """
    if ev.type == CanonEC.ObjectAddedEx and len(ev.raw) > 0x28:
        return CapturedObject(ev.u32(0x08), ev.u32(0x1C), ev.text(0x28)), ev.u16(0x10)
    if ev.type == CanonEC.ObjectAddedEx64 and len(ev.raw) > 0x2C:
        size = ev.u32(0x1C) | ev.u32(0x20) << 32
        return CapturedObject(ev.u32(0x08), size, ev.text(0x2C)), ev.u16(0x10)
    if ev.type == CanonEC.RequestObjectTransfer and len(ev.raw) > 0x1C:
        obj = CapturedObject(ev.u32(0x08), ev.u32(0x14), ev.text(0x1C), transfer=True)
        return obj, ev.u16(0x0C)
    return None


def property_data(prop: int, value: int) -> bytes:
    """SetDevicePropValueEx data of a u32 property: ``u32 size (12), u32 property, u32 value``."""
    return struct.pack("<III", 12, prop, value)


def is_eos_m(model: str) -> bool:
    """EOS M (mirrorless, EF-M) bodies need remote mode 0x15."""
    return model.startswith("Canon EOS M")


class CanonEOS(FocusCamera):
    vendor = "canon"
    stack_ops = (
        CanonOC.SetRemoteMode, CanonOC.SetEventMode, CanonOC.GetEvent,
        CanonOC.SetDevicePropValueEx, CanonOC.DriveLens, CanonOC.RemoteReleaseOn,
        CanonOC.RemoteReleaseOff, CanonOC.GetPartialObject, CanonOC.TransferComplete,
    )
    bulb_ops = stack_ops
    refusal_codes = (CanonRC.OperationRefused,)

    def setup(self) -> None:
        if self.drive_size not in (1, 2, 3):
            raise InputError(f"Canon DriveLens step size must be 1, 2 or 3, got {self.drive_size}")
        if self.drive_pace_s is None:
            self.drive_pace_s = DRIVE_PACE_S[self.drive_size]
        elif self.drive_pace_s < DRIVE_PACE_S[self.drive_size]:
            log.warning("DriveLens pace %.0f ms is below the default %.0f ms: bodies silently "
                        "drop a drive that arrives while the motor still runs, so focus_step "
                        "may not be where the lens is", self.drive_pace_s * 1e3,
                        DRIVE_PACE_S[self.drive_size] * 1e3)
        self.session.busy_codes |= {CanonRC.ObjectNotReady, CanonRC.MemoryStatusNotReady}
        self.status = 0
        self.properties: dict[int, int | str | bytes] = {}  # decoded (property_value)
        self.property_bytes: dict[int, bytes] = {}  # each value exactly as the camera sent it
        self._objects: list[CapturedObject] = []
        self._last_drive = -1e9
        info = self.session.device_info
        self.eos_m = bool(info and is_eos_m(info.model))

    # --- setup ------------------------------------------------------------------------------

    def start(self) -> None:
        s = self.session
        s.transaction(CanonOC.SetRemoteMode,
                      (CANON_REMOTE_MODE_EOS_M if self.eos_m else CANON_REMOTE_MODE,))
        s.transaction(CanonOC.SetEventMode, (1,))
        self.drain_events()
        self._check_lens_switch()
        if self.property_int(CanonDPC.EVFMode) != 1:
            self.set_property(CanonDPC.EVFMode, 1)
        self.set_property(CanonDPC.EVFOutputDevice, CANON_EVF_PC)
        self._poll("live view (EVFMode 1, EVF output to PC)", self._evf_on, timeout_s=10.0)

    def property_int(self, prop: int, default: int | None = None) -> int | None:
        """The last value of ``prop`` if it is a number, else ``default``."""
        value = self.properties.get(prop)
        return value if isinstance(value, int) else default

    def property_text(self, prop: int) -> str | None:
        """The last value of ``prop`` read as a NUL-terminated ASCII string (None if unseen)."""
        raw = self.property_bytes.get(prop)
        return None if raw is None else _text(raw)

    def _check_lens_switch(self) -> None:
        if self.property_int(CanonDPC.FocusMode) == CANON_FOCUS_MODE_MF:
            raise LensAtManual(
                "the lens focus switch is at MF (FocusMode 0xD108 = 3): the camera ignores "
                "DriveLens there; set the switch to AF (frames are shot with the no-AF release)"
            )

    def _evf_on(self):
        self.poll_events()
        on = (self.property_int(CanonDPC.EVFOutputDevice, 0) & CANON_EVF_PC
              and self.property_int(CanonDPC.EVFMode) == 1)
        return True if on else None

    def set_property(self, prop: int, value: int) -> None:
        """SetDevicePropValueEx of a u32 property (see :func:`property_data`)."""
        self.session.transaction(CanonOC.SetDevicePropValueEx, data_out=property_data(prop, value))

    # --- events -----------------------------------------------------------------------------

    def poll_events(self) -> list[CanonEvent]:
        """GetEvent once; remembers property values (whole), camera status and new images."""
        data = self.session.transaction(CanonOC.GetEvent, want_data=True).data
        events = parse_events(data)
        for ev in events:
            if ev.type == CanonEC.PropValueChanged and len(ev.raw) >= 12:
                prop, raw = ev.u32(8), ev.raw[12:]
                self.property_bytes[prop] = raw
                self.properties[prop] = property_value(prop, raw)
            elif ev.type == CanonEC.CameraStatusChanged and ev.words:
                self.status = ev.words[0]
            else:
                found = object_of(ev)
                if found is None:
                    continue
                obj, fmt = found
                if fmt == OBJECT_FORMAT_ASSOCIATION:
                    log.debug("skipping folder object %s", obj.filename)
                else:
                    self._objects.append(obj)
        return events

    def drain_events(self) -> None:
        """GetEvent until it returns no records (libgphoto2 does this before a capture)."""
        for _ in range(MAX_DRAIN):
            if not self.poll_events():
                return
        log.warning("camera kept reporting events; capturing anyway")

    # --- focus ------------------------------------------------------------------------------

    def drive_commands(self, steps: int) -> int:
        return abs(steps)  # one DriveLens per step of drive_size

    def _drive(self, steps: int) -> None:
        code = self.drive_size | (CANON_DRIVE_FAR if steps > 0 else 0)
        unit = 1 if steps > 0 else -1
        for _ in range(abs(steps)):
            self.clock.sleep(self._last_drive + self.drive_pace_s - self.clock.now())
            try:
                self.session.transaction(CanonOC.DriveLens, (code,))
            except PtpError as err:
                if err.code in self.refusal_codes:
                    raise DriveRefused(
                        f"{err} (live view off, or the shutter is open on a body that cannot "
                        "drive while exposing)", err.code) from err
                raise
            self._last_drive = self.clock.now()
            self.position += unit
            self.poll_events()

    def settle(self, seconds: float) -> None:
        """Wait for the motor (pace) and ``seconds``, take in the camera's events, and check
        the drives could have moved the lens (the switch was not turned to MF meanwhile)."""
        self.clock.sleep(self._last_drive + self.drive_pace_s - self.clock.now())
        self.clock.sleep(seconds)
        self.drain_events()
        self._check_lens_switch()

    # --- capture ----------------------------------------------------------------------------

    def capture(self) -> CapturedObject:
        self.open_exposure()
        return self.close_exposure()

    def open_exposure(self) -> None:
        self.settle(0.0)
        self._objects.clear()
        self.session.transaction(CanonOC.RemoteReleaseOn, (RELEASE_FULL, RELEASE_NO_AF))
        self.exposing = True

    def close_exposure(self) -> CapturedObject:
        self.session.transaction(CanonOC.RemoteReleaseOff, (RELEASE_FULL,))
        self.exposing = False
        return self._poll("waiting for the captured image (ObjectAddedEx / "
                          "RequestObjectTransfer)", self._next_object)

    def abort_exposure(self) -> None:
        if self.exposing:
            self._quietly("close the shutter", self.session.transaction,
                          CanonOC.RemoteReleaseOff, (RELEASE_FULL,))
            self.exposing = False

    def _next_object(self) -> CapturedObject | None:
        if not self._objects:
            self.poll_events()
        return self._objects.pop(0) if self._objects else None

    def _partial(self, obj: CapturedObject, offset: int, length: int) -> bytes:
        return self.session.transaction(
            CanonOC.GetPartialObject, (obj.handle, offset, length), want_data=True
        ).data

    def _download_done(self, obj: CapturedObject) -> None:
        if obj.transfer:  # held in RAM for the host: release it
            self.session.transaction(CanonOC.TransferComplete, (obj.handle,))

    def safe_state(self) -> None:
        self.abort_exposure()
        self._quietly("turn live view off", self.set_property, CanonDPC.EVFOutputDevice,
                      CANON_EVF_OFF)
        self._quietly("leave event mode", self.session.transaction, CanonOC.SetEventMode, (0,))
        self._quietly("leave remote mode", self.session.transaction, CanonOC.SetRemoteMode, (0,))
