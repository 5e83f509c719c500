"""Nikon: live view, MfDrive with DeviceReady polling, capture into SDRAM, download.

As in libgphoto2's ``camlibs/ptp2/config.c`` (``mfdrive``) and ``library.c``:
StartLiveView then DeviceReady until not busy; MfDrive(direction 1 near /
2 far, amount) then DeviceReady, whose MfDriveStepEnd (0xA00C) marks the end
stop and MfDriveStepInsufficiency (0xA00E) a step too small to move;
InitiateCaptureRecInSdram(0xFFFFFFFF = no AF), GetEvent for ObjectAddedInSDRAM,
GetObjectInfo and GetPartialObject.
"""

from __future__ import annotations

import struct

from pipeline.errors import InputError
from pipeline.tether.camera import CapturedObject, DriveRefused, EndStop, FocusCamera
from pipeline.tether.codes import (
    NIKON_MFDRIVE_FAR,
    NIKON_MFDRIVE_NEAR,
    NIKON_NO_AF,
    NIKON_SDRAM_HANDLE,
    OC,
    RC,
    NikonEC,
    NikonOC,
    NikonRC,
)
from pipeline.tether.ptp import ObjectInfo, ProtocolError

MAX_MFDRIVE = 32767


def parse_events(data: bytes) -> list[tuple[int, int]]:
    """Nikon GetEvent data: ``u16 count``, then ``count`` x (``u16 code, u32 parameter``)."""
    if len(data) < 2:
        return []
    (count,) = struct.unpack_from("<H", data)
    if len(data) < 2 + 6 * count:
        raise ProtocolError(f"Nikon GetEvent announces {count} events in {len(data)} bytes")
    return [struct.unpack_from("<HI", data, 2 + 6 * i) for i in range(count)]


def encode_events(events: list[tuple[int, int]]) -> bytes:
    """Inverse of :func:`parse_events` (for the emulator)."""
    return struct.pack("<H", len(events)) + b"".join(struct.pack("<HI", *e) for e in events)


class Nikon(FocusCamera):
    vendor = "nikon"
    stack_ops = (
        NikonOC.StartLiveView, NikonOC.EndLiveView, NikonOC.MfDrive, NikonOC.DeviceReady,
        NikonOC.InitiateCaptureRecInSdram, NikonOC.GetEvent, OC.GetObjectInfo,
        OC.GetPartialObject,
    )
    bulb_ops = (*stack_ops, NikonOC.TerminateCapture)
    refusal_codes = (NikonRC.NotLiveView,)

    def __post_init__(self) -> None:
        if self.drive_size != 1:
            raise InputError(f"Nikon MfDrive has no step sizes: --drive-size must be 1, "
                             f"got {self.drive_size}")
        self.live_view = False

    def start(self) -> None:
        self.session.transaction(NikonOC.StartLiveView)
        self.live_view = True
        self.wait_ready()

    def wait_ready(self) -> int:
        """Poll DeviceReady while it answers DeviceBusy; return its final code."""
        response = self.session.transaction(NikonOC.DeviceReady, check=False)
        if response.code not in (RC.OK, NikonRC.MfDriveStepEnd, NikonRC.MfDriveStepInsufficiency):
            self.session.check(NikonOC.DeviceReady, response)
        return response.code

    def _drive(self, steps: int) -> None:
        direction = NIKON_MFDRIVE_FAR if steps > 0 else NIKON_MFDRIVE_NEAR
        amount = abs(steps)
        if amount > MAX_MFDRIVE:
            raise InputError(f"Nikon MfDrive moves at most {MAX_MFDRIVE} steps, got {amount}")
        response = self.session.transaction(NikonOC.MfDrive, (direction, amount), check=False)
        code = response.code
        if code == RC.OK:
            code = self.wait_ready()
        side = "far" if steps > 0 else "near"
        if code == NikonRC.MfDriveStepEnd:
            raise EndStop(
                f"focus drive reached the {side} end stop (Nikon MfDriveStepEnd 0xA00C) "
                f"at {self.position} steps from the start; use fewer frames, a smaller step "
                "or start further from that end"
            )
        if code == NikonRC.MfDriveStepInsufficiency:
            raise InputError(
                f"MfDrive of {amount} steps is too small for this lens "
                "(Nikon MfDriveStepInsufficiency 0xA00E); use a larger --step"
            )
        if code in self.refusal_codes:
            raise DriveRefused("MfDrive refused: live view is off (camera exposing?)", code)
        if code != RC.OK:
            self.session.check(NikonOC.MfDrive, response)

    def capture(self) -> CapturedObject:
        self.open_exposure()
        return self._fetch_captured()

    def open_exposure(self) -> None:
        self.session.transaction(NikonOC.InitiateCaptureRecInSdram, (NIKON_NO_AF,))

    def close_exposure(self) -> CapturedObject:
        """End a bulb exposure (TerminateCapture) and fetch the image's handle and size."""
        self.session.transaction(NikonOC.TerminateCapture, (0, 0))
        return self._fetch_captured()

    def _fetch_captured(self) -> CapturedObject:
        self.wait_ready()
        handle = self._poll("waiting for the captured image (ObjectAddedInSDRAM)",
                            self._added_handle)
        info = ObjectInfo.from_bytes(
            self.session.transaction(OC.GetObjectInfo, (handle,), want_data=True).data
        )
        return CapturedObject(handle, info.size, info.filename)

    def _added_handle(self) -> int | None:
        data = self.session.transaction(NikonOC.GetEvent, want_data=True).data
        for code, param in parse_events(data):
            if code == NikonEC.ObjectAddedInSDRAM:
                return param or NIKON_SDRAM_HANDLE
        return None

    def _partial(self, obj: CapturedObject, offset: int, length: int) -> bytes:
        return self.session.transaction(
            OC.GetPartialObject, (obj.handle, offset, length), want_data=True
        ).data

    def safe_state(self) -> None:
        if self.live_view:
            self._quietly("end live view", self.session.transaction, NikonOC.EndLiveView)
            self.live_view = False

