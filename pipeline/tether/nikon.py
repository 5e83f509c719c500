"""Nikon: live view, MfDrive with DeviceReady polling, capture into SDRAM, download, delete.

As libgphoto2 documents it (``camlibs/ptp2/config.c`` ``mfdrive``, ``library.c``):
StartLiveView then DeviceReady until not busy; MfDrive(direction 1 near /
2 far, amount) then DeviceReady, whose MfDriveStepEnd (0xA00C) marks the end
stop and MfDriveStepInsufficiency (0xA00E) a step too small to move;
InitiateCaptureRecInSdram(0xFFFFFFFF = no AF), DeviceReady (busy, 0x2019 or
0xA200, for as long as the body processes: seconds after a long exposure),
GetEvent for ObjectAddedInSDRAM, GetObjectInfo, GetPartialObject, then
DeleteObject (an image left in SDRAM blocks live view and the next capture).

Bodies end live view when they shoot; it is restarted before the next drive
(LiveViewStatus 0xD1A2 when the body reports it). Live view is prohibited in
bulb, and MfDrive needs live view, so a focus sweep (bulb while driving) is
refused on Nikon bodies.
"""

from __future__ import annotations

import struct

from pipeline.errors import InputError
from pipeline.tether.base import CapturedObject, DriveRefused, EndStop, FocusCamera
from pipeline.tether.codes import (
    NIKON_MFDRIVE_FAR,
    NIKON_MFDRIVE_NEAR,
    NIKON_NO_AF,
    NIKON_SDRAM_HANDLE,
    OC,
    RC,
    NikonDPC,
    NikonEC,
    NikonOC,
    NikonRC,
)
from pipeline.tether.ptp import ObjectInfo, ProtocolError
from pipeline.tether.session import CameraBusy, UnsupportedCamera

MAX_MFDRIVE = 32767
READY_BUSY = (RC.DeviceBusy, NikonRC.BulbReleaseBusy)
READY_POLL_S = 0.05
READY_TIMEOUT_S = 60.0  # after a capture: exposure, noise reduction, writing


def parse_events(data: bytes) -> list[tuple[int, int]]:
    """Nikon GetEvent data: ``u16 count``, then ``count`` x (``u16 code, u32 parameter``)."""
    if len(data) < 2:
        return []
    (count,) = struct.unpack_from("<H", data)
    if len(data) < 2 + 6 * count:
        raise ProtocolError(f"Nikon GetEvent announces {count} events in {len(data)} bytes")
    return [struct.unpack_from("<HI", data, 2 + 6 * i) for i in range(count)]


class Nikon(FocusCamera):
    vendor = "nikon"
    stack_ops = (
        NikonOC.StartLiveView, NikonOC.EndLiveView, NikonOC.MfDrive, NikonOC.DeviceReady,
        NikonOC.InitiateCaptureRecInSdram, NikonOC.GetEvent, OC.GetObjectInfo,
        OC.GetPartialObject, OC.DeleteObject,
    )
    refusal_codes = (NikonRC.NotLiveView,)
    # MfDrive needs live view, which Nikon bodies prohibit in bulb
    sweep_refusal = "Nikon: sweep not supported (live view is prohibited in bulb; no bulb path)"

    def setup(self) -> None:
        if self.drive_size != 1:
            raise InputError(f"Nikon MfDrive has no step sizes: --drive-size must be 1, "
                             f"got {self.drive_size}")
        if self.drive_pace_s is None:
            self.drive_pace_s = 0.0  # DeviceReady already waits for the motor
        self.live_view = False
        self._lv_stale = False  # a capture may have ended live view

    def start(self) -> None:
        self.start_live_view()

    def open_exposure(self) -> None:
        raise UnsupportedCamera(f"{self.sweep_refusal}; capture a focal stack (tether stack) "
                                "instead")

    def start_live_view(self) -> None:
        """StartLiveView, then DeviceReady until it is up."""
        response = self.session.transaction(NikonOC.StartLiveView, check=False)
        if response.code != RC.OK:
            self.session.check(NikonOC.StartLiveView, response)
        self.wait_ready(timeout_s=10.0)
        self.live_view = True
        self._lv_stale = False

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> int:
        """Poll DeviceReady while busy (0x2019, 0xA200 bulb release busy); its final code."""
        deadline = self.clock.now() + timeout_s
        while True:
            response = self.session.transaction(NikonOC.DeviceReady, check=False, busy_ok=False)
            if response.code not in READY_BUSY:
                break
            if self.clock.now() > deadline:
                raise CameraBusy(f"camera still busy after {timeout_s:.0f} s (DeviceReady "
                                 f"0x{response.code:04X}); check the camera", response.code)
            self.clock.sleep(READY_POLL_S)
        if response.code not in (RC.OK, NikonRC.MfDriveStepEnd,
                                 NikonRC.MfDriveStepInsufficiency):
            self.session.check(NikonOC.DeviceReady, response)
        return response.code

    def _live_view_on(self) -> bool:
        """LiveViewStatus if the body reports it; otherwise assume a capture ended it."""
        if self.session.supports(OC.GetDevicePropValue):
            response = self.session.transaction(OC.GetDevicePropValue,
                                                (NikonDPC.LiveViewStatus,), want_data=True,
                                                check=False)
            if response.code == RC.OK and response.data:
                return bool(response.data[0])
        return False

    def _ensure_live_view(self) -> None:
        if self._lv_stale and not self._live_view_on():
            self.start_live_view()
        self._lv_stale = False

    def _drive(self, steps: int) -> None:
        direction = NIKON_MFDRIVE_FAR if steps > 0 else NIKON_MFDRIVE_NEAR
        amount = abs(steps)
        if amount > MAX_MFDRIVE:
            raise InputError(f"Nikon MfDrive moves at most {MAX_MFDRIVE} steps, got {amount}")
        self._ensure_live_view()
        response = self.session.transaction(NikonOC.MfDrive, (direction, amount), check=False)
        if response.code == NikonRC.NotLiveView and not self.exposing:
            self.start_live_view()  # the body ended it (e.g. after a capture): once more
            response = self.session.transaction(NikonOC.MfDrive, (direction, amount),
                                                check=False)
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
            raise DriveRefused("MfDrive refused: live view is off and could not be restarted",
                               code)
        if code != RC.OK:
            self.session.check(NikonOC.MfDrive, response)
        self.position += steps

    def capture(self) -> CapturedObject:
        self.session.transaction(NikonOC.InitiateCaptureRecInSdram, (NIKON_NO_AF,))
        self._lv_stale = True
        self.wait_ready()
        handle = self._poll("waiting for the captured image (ObjectAddedInSDRAM)",
                            self._added_handle)
        info = ObjectInfo.from_bytes(
            self.session.transaction(OC.GetObjectInfo, (handle,), want_data=True).data
        )
        return CapturedObject(handle, info.size, info.filename, transfer=True)

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

    def _download_done(self, obj: CapturedObject) -> None:
        self.session.transaction(OC.DeleteObject, (obj.handle,))

    def safe_state(self) -> None:
        if self.live_view:
            self._quietly("end live view", self.session.transaction, NikonOC.EndLiveView)
            self.live_view = False
