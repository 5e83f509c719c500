"""An emulated PTP camera as a pyusb backend (``usb.backend.IBackend``), no monkey-patching.

``usb.core.find(backend=EmulatedBackend(EmulatedCamera(CANON)))`` gives a real
``usb.core.Device``; every byte goes through pyusb's endpoint and control
transfer code into this backend. The camera is strict and independent of the
host code: its replies are built from :mod:`.layouts` (the documented byte
layouts), and it models what real bodies do to a careless host:

* bulk-in as a stream of packets: a container ending on a packet boundary is
  followed by a zero-length packet unless the personality omits it; a read ends
  at a short packet, so without the ZLP the next container runs into the read;
* an AF model: the AF release (RemoteReleaseOn second parameter 0) refocuses
  the lens and does not fire if AF fails; the MF release (1) does neither; a
  lens switch at MF makes DriveLens do nothing (answered OK);
* live view needs EVFMode = 1 and the PC bit of EVFOutputDevice (and, on EOS M,
  remote mode 0x15); Nikon bodies drop live view on a capture, refuse it in
  bulb and while an image waits in SDRAM;
* a focus motor that takes time: a drive arriving while it runs is dropped or
  busy (per personality); RemoteReleaseOn with undrained events is busy;
* Nikon DeviceReady busy for seconds after a capture (0x2019, or 0xA200);
* Canon CaptureDestination honoured (card: ObjectAddedEx or ObjectAddedEx64 and
  a folder object first; PC: RequestObjectTransfer and TransferComplete);
* faults: busy, stall, timeout, unplug mid-transfer, error codes, stray ZLPs.

Time is the camera's ``clock`` (a :class:`~pipeline.tether.clock.VirtualClock`
by default, shared with the host through the backend); every transaction
takes 1 ms of it.
"""

from __future__ import annotations

import errno
import itertools
import struct
from collections import deque
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import usb.backend
import usb.core

from pipeline.tether.clock import VirtualClock
from pipeline.tether.emulated import layouts
from pipeline.tether.emulated.personalities import CANON, NIKON, Personality, personality
from pipeline.tether.emulated.scene import encode_jpeg, encode_tiff16, render_frame
from pipeline.tether.host_backend import TIMEOUT, HostBackend

BULK_IN, BULK_OUT, INTR_IN = 0x81, 0x02, 0x83
_ENODEV = (-4, errno.ENODEV)  # LIBUSB_ERROR_NO_DEVICE
_EPIPE = (-9, errno.EPIPE)  # LIBUSB_ERROR_PIPE

# numbers spelled out here (ISO 15740, libgphoto2 ptp.h) rather than imported from the host
OK, GENERAL_ERROR, SESSION_NOT_OPEN = 0x2001, 0x2002, 0x2003
OP_NOT_SUPPORTED, PARAM_NOT_SUPPORTED, INCOMPLETE_TRANSFER = 0x2005, 0x2006, 0x2007
INVALID_HANDLE, DEVICE_BUSY, INVALID_PARAMETER, SESSION_OPEN = 0x2009, 0x2019, 0x201D, 0x201E
CANON_REFUSED = 0xA005
NIKON_INVALID_STATUS, NIKON_NOT_LIVE_VIEW = 0xA004, 0xA00B
NIKON_STEP_END, NIKON_STEP_INSUFFICIENT, NIKON_BULB_BUSY = 0xA00C, 0xA00E, 0xA200
DATA_OUT_OPS = {0x9110, 0x1016}  # SetDevicePropValueEx, SetDevicePropValue
EOS_FOCUS_MODE, EOS_CAPTURE_DEST, EOS_EVF_OUTPUT, EOS_EVF_MODE = 0xD108, 0xD11C, 0xD1B0, 0xD1B1
NIKON_LV_STATUS, NIKON_LV_PROHIBIT = 0xD1A2, 0xD1A4
NIKON_SDRAM_HANDLE = 0xFFFF0001
FOLDER_FORMAT, JPEG_FORMAT, TIFF_FORMAT = 0x3001, 0x3801, 0x380D


@dataclass
class Faults:
    """Faults to switch on. Counters and one-shot entries are used up as they fire."""

    busy_responses: int = 0  # next N drive/capture/download commands answer DeviceBusy
    busy_ops: frozenset = frozenset({0x9155, 0x9204, 0x9128, 0x90C0, 0x9107, 0x101B})
    stall_on: int | None = None  # stall bulk-in on the next command with this opcode
    timeout_on: int | None = None  # never answer the next command with this opcode
    unplug_on_download: int | None = None  # vanish mid data phase of the k-th download
    error_on: dict = field(default_factory=dict)  # opcode -> response code, once
    stray_zlp: bool = False  # a zero-length packet before every response container
    ready_busy_code: int = DEVICE_BUSY  # what Nikon DeviceReady answers while busy
    af_succeeds: bool = True  # AF finds focus (else an AF release does not fire)


@dataclass
class StoredObject:
    name: str
    blob: bytes
    fmt: int
    transfer: bool = False  # Canon: held in RAM until TransferComplete


class EmulatedCamera:
    """The device side: descriptors, wire protocol, PTP state machine, motor, shutter.

    Parameters
    ----------
    personality : Personality
        The body to play (:mod:`.personalities`).
    faults : Faults, optional
    position : int
        Motor position at power-on, in motor units.
    limits : tuple of int
        Motor end stops.
    shutter : str
        ``"normal"`` or ``"bulb"`` (the mode dial).
    af_target : int
        Where the AF puts the motor when an AF release refocuses.
    clock : VirtualClock, optional
        Shared with the host through :class:`EmulatedBackend`.
    """

    def __init__(
        self,
        personality: Personality = CANON,
        *,
        faults: Faults | None = None,
        position: int = 0,
        limits: tuple[int, int] = (0, 400),
        shutter: str = "normal",
        af_target: int = 200,
        renderer=render_frame,
        clock=None,
        bus: int = 1,
        address: int = 5,
    ) -> None:
        self.p = personality
        self.faults = faults or Faults()
        self.clock = clock if clock is not None else VirtualClock()
        self.position = position
        self.limits = limits
        self.shutter = shutter
        self.af_target = af_target
        self.renderer = renderer
        self.bus, self.address = bus, address
        self.plugged = True
        self._power_on()
        # logs the tests compare against
        self.motor_log: list[tuple[float, int]] = [(self.clock.now(), position)]
        self.shots: list[tuple[int, int]] = []  # (handle, motor position at the shot)
        self.transactions: list[tuple[int, int, tuple]] = []  # (tid, opcode, params)
        self.busy_given = 0
        self.dropped_drives = 0
        self.af_refocused = 0
        self.af_failures = 0
        self.cancelled: list[int] = []
        self.halts_cleared: list[int] = []
        self.zlps_received = 0
        self.downloads_started = 0
        self.max_sdram_pending = 0

    def _power_on(self) -> None:
        """PTP state after power-on or a device reset (the motor stays where it is)."""
        self.session_open = False
        self.remote_mode = 0
        self.event_mode = 0
        self.properties: dict[int, int] = {
            EOS_FOCUS_MODE: self.p.focus_mode, EOS_CAPTURE_DEST: self.p.capture_destination,
            EOS_EVF_OUTPUT: 0, EOS_EVF_MODE: self.p.evf_mode,
        }
        self.live_view = False
        self.exposing = False
        self._exposure: list[tuple[float, int]] = []
        self.objects: dict[int, StoredObject] = {}
        self._next_handle = 0x1001
        self._folder_made = False
        self._events: list = []
        self._delayed: list[tuple[float, bytes]] = []  # (due time, record)
        self._dumped = False
        self._chatter_at = self.clock.now() + self.p.chatter_s
        self._motor_until = 0.0
        self._ready_until = 0.0
        self._ready_result = OK
        self._in = bytearray()
        self._command: tuple[int, int, tuple] | None = None
        self._expect_zlp = False
        self._packets: deque[bytes] = deque()
        self._stalled = False
        self._hanging: int | None = None
        self._unplug_after: int | None = None

    # --- derived state ---------------------------------------------------------------------

    @property
    def evf_on(self) -> bool:
        """Canon live view runs: EVFMode 1 and the PC bit of EVFOutputDevice."""
        return self.properties[EOS_EVF_MODE] == 1 and bool(self.properties[EOS_EVF_OUTPUT] & 2)

    @property
    def lens_at_mf(self) -> bool:
        return self.properties[EOS_FOCUS_MODE] == 3

    @property
    def sdram(self) -> list[int]:
        """Handles of images waiting in camera RAM for the host."""
        return [h for h, o in self.objects.items() if o.transfer]

    @property
    def motor_moving(self) -> bool:
        return self.clock.now() < self._motor_until

    # --- wire level: bulk out ---------------------------------------------------------------

    def host_write(self, data: bytes) -> int:
        self._alive()
        if self._stalled:
            raise usb.core.USBError("Pipe error", *_EPIPE)
        if not data:
            if not self._expect_zlp:
                raise AssertionError("host sent a zero-length packet that was not due")
            self._expect_zlp = False
            self.zlps_received += 1
            return 0
        if self._expect_zlp:
            raise AssertionError("host sent a new transfer before the due zero-length packet")
        self._in += data
        if len(self._in) >= 12:
            length = struct.unpack_from("<I", self._in)[0]
            if len(self._in) >= length:
                blob, self._in = bytes(self._in[:length]), self._in[length:]
                self._expect_zlp = length % self.p.packet_size == 0
                self._container_in(blob)
        return len(data)

    def _container_in(self, blob: bytes) -> None:
        length, kind, code, tid = struct.unpack_from("<IHHI", blob)
        if kind == 1:  # command
            count = (length - 12) // 4
            self._command = (code, tid, struct.unpack_from(f"<{count}I", blob, 12))
            if code not in DATA_OUT_OPS:
                self._run(None)
        elif kind == 2 and self._command is not None:  # data phase of a data-out operation
            self._run(blob[12:])
        else:
            raise AssertionError(f"host sent a container of type {kind} out of order")

    # --- wire level: bulk in ----------------------------------------------------------------

    def _queue(self, blob: bytes) -> None:
        ps = self.p.packet_size
        self._packets.extend(blob[i : i + ps] for i in range(0, len(blob), ps))
        if len(blob) % ps == 0 and not self.p.omit_zlp:
            self._packets.append(b"")

    def host_read(self, size: int) -> bytes:
        """One bulk-in transfer: packets until ``size`` bytes or a short packet."""
        self._alive()
        if self._stalled:
            raise usb.core.USBError("Pipe error", *_EPIPE)
        if self._hanging is not None or not self._packets:
            raise usb.core.USBTimeoutError("Operation timed out", *TIMEOUT)
        if size % self.p.packet_size:
            raise AssertionError(f"bulk-in read of {size} bytes is not a multiple of the packet")
        out = bytearray()
        while self._packets and len(out) < size:
            packet = self._packets.popleft()
            out += packet
            if self._unplug_after is not None:
                self._unplug_after -= 1
                if self._unplug_after <= 0:
                    self._unplug_after = None
                    self.plugged = False
                    break
            if len(packet) < self.p.packet_size:
                break
        return bytes(out)

    def _alive(self) -> None:
        if not self.plugged:
            raise usb.core.USBError("No such device (it may have been disconnected)", *_ENODEV)

    def set_lens_switch(self, mode: str) -> None:
        """The user moves the lens focus switch to ``"AF"`` or ``"MF"`` (Canon FocusMode event)."""
        self.properties[EOS_FOCUS_MODE] = 3 if mode == "MF" else 0
        if self.event_mode:
            self._events.append(layouts.eos_prop_value(EOS_FOCUS_MODE,
                                                       self.properties[EOS_FOCUS_MODE]))

    def unplug(self) -> None:
        """Pull the cable: every later transfer fails with ENODEV."""
        self.plugged = False

    # --- class requests ---------------------------------------------------------------------

    def class_request(self, request: int, data: bytes | None, length: int) -> bytes | int:
        self._alive()
        if request == 0x64:  # cancel
            _code, tid = struct.unpack("<HI", bytes(data))
            self.cancelled.append(tid)
            self._hanging = None
            self._packets.clear()
            self._command = None
            return len(data)
        if request == 0x66:  # device reset
            self._power_on()
            return 0
        if request == 0x67:  # get device status
            if self._stalled:
                return struct.pack("<HHI", 8, INCOMPLETE_TRANSFER, BULK_IN)
            return struct.pack("<HH", 4, DEVICE_BUSY if self._hanging is not None else OK)
        raise usb.core.USBError("Pipe error", *_EPIPE)

    def clear_halt(self, ep: int) -> None:
        self._alive()
        self.halts_cleared.append(ep)
        if ep == BULK_IN:
            self._stalled = False
            self._packets.clear()

    # --- PTP --------------------------------------------------------------------------------

    def _run(self, data_out: bytes | None) -> None:
        code, tid, args = self._command
        self._command = None
        self.transactions.append((tid, code, args))
        self.clock.advance(0.001)
        f = self.faults
        if f.timeout_on == code:
            f.timeout_on = None
            self._hanging = tid
            return
        if f.stall_on == code:
            f.stall_on = None
            self._stalled = True
            return
        if f.busy_responses and code in f.busy_ops and self.session_open:
            f.busy_responses -= 1
            rc, out_params, data = DEVICE_BUSY, (), None
        elif code in f.error_on and self.session_open:
            rc, out_params, data = f.error_on.pop(code), (), None
        else:
            rc, out_params, data = self._operate(code, args, data_out)
        if rc in (DEVICE_BUSY, NIKON_BULB_BUSY):
            self.busy_given += 1
        if data is not None:
            self._queue(layouts.container(2, code, tid, data))
        if f.stray_zlp:
            self._packets.append(b"")
        self._queue(layouts.container(3, rc, tid, layouts.params(*out_params)))

    def _operate(self, op: int, args: tuple, data_out: bytes | None):
        """(response code, response params, data-in payload or None)."""
        if op not in self.p.operations:
            return OP_NOT_SUPPORTED, (), None
        if op == 0x1001:  # GetDeviceInfo
            return OK, (), self.device_info()
        if op == 0x1002:  # OpenSession
            if self.session_open:
                return SESSION_OPEN, (), None
            self.session_open = True
            return OK, (), None
        if not self.session_open:
            return SESSION_NOT_OPEN, (), None
        if op == 0x1003:  # CloseSession
            self.session_open = False
            return OK, (), None
        if self.p.chatter_s and self.event_mode and self.clock.now() >= self._chatter_at:
            self._chatter_at = self.clock.now() + self.p.chatter_s
            self._events.append(layouts.eos_prop_value(0xD1AB, 0))  # TempStatus: normal
        handler = getattr(self, f"_{self.p.vendor}_{op:04x}", None) or getattr(
            self, f"_std_{op:04x}", None)
        if handler is None:
            return PARAM_NOT_SUPPORTED, (), None
        return handler(*args, data=data_out)

    def device_info(self) -> bytes:
        return layouts.device_info(
            vendor_extension_id=self.p.vendor_extension_id, manufacturer=self.p.manufacturer,
            model=self.p.model, operations=self.p.listed_operations,
        )

    # --- standard operations ----------------------------------------------------------------

    def _std_101b(self, handle=0, offset=0, length=0, *_, data=None):  # GetPartialObject
        return self._partial(handle, offset, length)

    def _std_1008(self, handle=0, *_, data=None):  # GetObjectInfo
        obj = self.objects.get(handle)
        if obj is None:
            return INVALID_HANDLE, (), None
        return OK, (), layouts.object_info(storage=0x00010001, fmt=obj.fmt, size=len(obj.blob),
                                           name=obj.name)

    def _std_100b(self, handle=0, *_, data=None):  # DeleteObject
        if self.objects.pop(handle, None) is None:
            return INVALID_HANDLE, (), None
        return OK, (), None

    def _std_1015(self, prop=0, *_, data=None):  # GetDevicePropValue
        if self.p.vendor == "nikon" and prop == NIKON_LV_STATUS:
            return OK, (), layouts.device_prop_value_u8(int(self.live_view))
        if self.p.vendor == "nikon" and prop == NIKON_LV_PROHIBIT:
            return OK, (), struct.pack("<I", self._lv_prohibited())
        return PARAM_NOT_SUPPORTED, (), None

    def _partial(self, handle, offset, length):
        obj = self.objects.get(handle)
        if obj is None:
            return INVALID_HANDLE, (), None
        if offset == 0:
            if self.faults.unplug_on_download == self.downloads_started:
                chunk_packets = -(-(12 + min(length, len(obj.blob))) // self.p.packet_size)
                self._unplug_after = max(1, chunk_packets // 2)
            self.downloads_started += 1
        chunk = obj.blob[offset : offset + length]
        return OK, (len(chunk),), chunk

    # --- motor and shutter ------------------------------------------------------------------

    def _move(self, steps: int) -> bool:
        """Drive the motor; False if it stopped at a limit."""
        lo, hi = self.limits
        target = self.position + steps
        self.position = min(max(target, lo), hi)
        now = self.clock.now()
        if self.exposing:
            self._exposure.append((now, self.position))
        self.motor_log.append((now, self.position))
        return self.position == target

    def _open_shutter(self) -> None:
        self.exposing = True
        self._exposure = [(self.clock.now(), self.position)]

    def _close_shutter(self, *, transfer: bool) -> int:
        """End the exposure: render (time-weighted over motor positions), store; its handle."""
        self.exposing = False
        marks = [*self._exposure, (self.clock.now(), self.position)]
        dwell = np.array([max(b[0] - a[0], 0.0) for a, b in itertools.pairwise(marks)])
        positions = [pos for _t, pos in marks[:-1]]
        if len(set(positions)) == 1 or dwell.sum() <= 0:
            image = self.renderer(positions[-1])
        else:
            image = sum(w * self.renderer(pos) for w, pos in zip(dwell / dwell.sum(), positions))
            image = np.clip(image, 0.0, 1.0)  # a mean of [0, 1] frames, up to rounding
        if self.p.vendor == "nikon":
            handle = NIKON_SDRAM_HANDLE
        else:
            handle = self._next_handle
            self._next_handle += 1
        n = len(self.shots) + 1
        if self.p.image_format == "jpeg":
            obj = StoredObject(f"IMG_{n:04d}.JPG", encode_jpeg(image), JPEG_FORMAT, transfer)
        else:
            obj = StoredObject(f"DSC_{n:04d}.TIF", encode_tiff16(image), TIFF_FORMAT, transfer)
        self.objects[handle] = obj
        self.shots.append((handle, self.position))
        self.max_sdram_pending = max(self.max_sdram_pending, len(self.sdram))
        return handle

    # --- Canon EOS operations (method name: _canon_<opcode hex>) ----------------------------

    def _canon_9114(self, mode=0, *_, data=None):  # SetRemoteMode
        self.remote_mode = mode
        return OK, (), None

    def _canon_9115(self, mode=0, *_, data=None):  # SetEventMode
        self.event_mode = mode
        if mode and not self._dumped:  # the first GetEvent reports every property
            self._dumped = True
            self._events += [layouts.eos_prop_value(p, v) for p, v in self.properties.items()]
            self._events += [layouts.eos_prop_value(0xD101, 0x30), layouts.eos_camera_status(0)]
            # values that are not one u32, as the 60D sends them: Owner (one byte), serial
            # number (a string), lens name (a 64-byte string field)
            self._events += [layouts.eos_prop_raw(0xD115, b"\x00"),
                             layouts.eos_prop_raw(0xD1AF, b"EMU0001\x00"),
                             layouts.eos_prop_raw(0xD1D8, b"EF50mm f/1.8 (emulated)".ljust(64,
                                                                                   b"\x00"))]
        return OK, (), None

    def _canon_9110(self, *_, data=None):  # SetDevicePropValueEx
        if data is None or len(data) < 12:
            return INVALID_PARAMETER, (), None
        size, prop, value = struct.unpack_from("<III", data)
        if size != len(data):
            return INVALID_PARAMETER, (), None
        if prop == EOS_FOCUS_MODE:  # set by the lens switch, not by the host
            return CANON_REFUSED, (), None
        self.properties[prop] = value
        self._events.append(layouts.eos_prop_value(prop, value))
        return OK, (), None

    def _canon_9116(self, *_, data=None):  # GetEvent
        now = self.clock.now()
        self._events += [r for due, r in self._delayed if due <= now]
        self._delayed = [(due, r) for due, r in self._delayed if due > now]
        records, self._events = self._events, []
        return OK, (), b"".join(records) + layouts.EOS_TERMINATOR

    def _canon_9155(self, code=0, *_, data=None):  # DriveLens
        if self.remote_mode != self.p.remote_mode or not self.evf_on:
            return CANON_REFUSED, (), None
        if self.exposing and not self.p.drive_while_exposing:
            return CANON_REFUSED, (), None
        size = code & 0x3
        if size not in self.p.steps_per_size or code & ~0x8003:
            return INVALID_PARAMETER, (), None
        if self.lens_at_mf:
            return OK, (), None  # the body ignores it silently
        if self.motor_moving:
            if self.p.drive_overlap == "busy":
                return DEVICE_BUSY, (), None
            self.dropped_drives += 1
            return OK, (), None
        steps = self.p.steps_per_size[size]
        self._move(steps if code & 0x8000 else -steps)  # EOS stops silently at a limit
        self._motor_until = self.clock.now() + self.p.drive_s[size]
        return OK, (), None

    def _canon_9128(self, press=0, af=0, *_, data=None):  # RemoteReleaseOn
        if self._events:
            return DEVICE_BUSY, (), None  # libgphoto2 drains events first, else busy
        if press & 2 and not self.exposing:
            if af == 0 and not self.lens_at_mf:
                if not self.faults.af_succeeds:
                    self.af_failures += 1
                    return OK, (), None  # AF failed: the shutter does not release
                self.af_refocused += 1
                self._move(self.af_target - self.position)
            self._open_shutter()
            self._events.append(layouts.eos_camera_status(1))
            if self.shutter != "bulb":
                self._canon_image()
        return OK, (), None

    def _canon_9129(self, press=0, *_, data=None):  # RemoteReleaseOff
        if press & 2 and self.exposing and self.shutter == "bulb":
            self._canon_image()
        return OK, (), None

    def _canon_image(self) -> None:
        to_pc = self.properties[EOS_CAPTURE_DEST] == 4
        handle = self._close_shutter(transfer=to_pc)
        obj = self.objects[handle]
        self._events.append(layouts.eos_camera_status(0))
        due = self.clock.now() + self.p.image_delay_s
        if to_pc:
            self._delayed.append((due, layouts.eos_request_transfer(handle, len(obj.blob),
                                                                    obj.name, obj.fmt)))
            return
        added = layouts.eos_object_added64 if self.p.object_event == "ex64" else \
            layouts.eos_object_added
        if not self._folder_made:  # the first image on the card opens a new folder
            self._folder_made = True
            self._delayed.append((due, added(0x00100000, 0, "100CANON", FOLDER_FORMAT,
                                             parent=0xFFFFFFFF)))
        self._delayed.append((due, added(handle, len(obj.blob), obj.name, obj.fmt)))

    def _canon_9107(self, handle=0, offset=0, length=0, *_, data=None):  # GetPartialObject
        return self._partial(handle, offset, length)

    def _canon_9117(self, handle=0, *_, data=None):  # TransferComplete
        obj = self.objects.get(handle)
        if obj is None or not obj.transfer:
            return INVALID_HANDLE, (), None  # only for images held for the host
        del self.objects[handle]
        return OK, (), None

    # --- Nikon operations (method name: _nikon_<opcode hex>) --------------------------------

    def _lv_prohibited(self) -> int:
        """LiveViewProhibitCondition bits: bulb (bit 2 here), image pending in SDRAM (bit 9)."""
        return (4 if self.shutter == "bulb" else 0) | (0x200 if self.sdram else 0)

    def _nikon_busy(self) -> bool:
        return self.clock.now() < self._ready_until

    def _nikon_9201(self, *_, data=None):  # StartLiveView
        if self._nikon_busy():
            return DEVICE_BUSY, (), None
        if self._lv_prohibited():
            return NIKON_INVALID_STATUS, (), None
        self.live_view = True
        self._ready_until = self.clock.now() + 0.5
        return OK, (), None

    def _nikon_9202(self, *_, data=None):  # EndLiveView
        self.live_view = False
        return OK, (), None

    def _nikon_90c8(self, *_, data=None):  # DeviceReady
        if self.exposing and self.shutter == "bulb":
            return NIKON_BULB_BUSY, (), None  # bulb release busy until TerminateCapture
        if self._nikon_busy():
            return (self.faults.ready_busy_code if self._ready_after_capture else DEVICE_BUSY,
                    (), None)
        result, self._ready_result = self._ready_result, OK
        return result, (), None

    _ready_after_capture = False

    def _nikon_9204(self, direction=0, amount=0, *_, data=None):  # MfDrive
        if not self.live_view:
            return NIKON_NOT_LIVE_VIEW, (), None
        if self._nikon_busy():
            return DEVICE_BUSY, (), None
        if direction not in (1, 2):
            return INVALID_PARAMETER, (), None
        if amount < 1:
            self._ready_result = NIKON_STEP_INSUFFICIENT
        elif not self._move(amount if direction == 2 else -amount):
            self._ready_result = NIKON_STEP_END
        self._ready_after_capture = False
        self._ready_until = self.clock.now() + 0.02 + amount * self.p.drive_s[1]
        return OK, (), None

    def _nikon_90c0(self, *_, data=None):  # InitiateCaptureRecInSdram
        if self._nikon_busy():
            return DEVICE_BUSY, (), None
        if self.sdram:
            return NIKON_INVALID_STATUS, (), None  # one image at a time in SDRAM
        self._open_shutter()
        if self.shutter != "bulb":
            self._nikon_captured()
        return OK, (), None

    def _nikon_920c(self, *_, data=None):  # TerminateCapture
        if self.exposing:
            self._nikon_captured()
        return OK, (), None

    def _nikon_captured(self) -> None:
        handle = self._close_shutter(transfer=True)
        self._events.append((0xC101, handle))  # ObjectAddedInSDRAM
        self._ready_after_capture = True
        self._ready_until = self.clock.now() + self.p.ready_busy_s
        if self.p.drops_live_view:
            self.live_view = False

    def _nikon_90c7(self, *_, data=None):  # GetEvent
        events, self._events = self._events, []
        return OK, (), layouts.nikon_events(events)

    # --- USB descriptors --------------------------------------------------------------------

    def strings(self) -> dict[int, str]:
        return {1: self.p.manufacturer, 2: self.p.model, 3: "EMU0001"}


@dataclass
class OtherDevice:
    """A non-camera USB device (to test what is listed when no camera is found)."""

    id_vendor: int = 0x1D6B
    id_product: int = 0x0002
    device_class: int = 9  # hub
    bus: int = 1
    address: int = 1


class EmulatedBackend(HostBackend):
    """A pyusb backend whose devices are :class:`EmulatedCamera` (and :class:`OtherDevice`).

    :attr:`clock` is the first camera's clock, for the host to share.
    """

    def __init__(self, *devices) -> None:
        super().__init__()
        self.devices = list(devices)
        cams = [d for d in devices if isinstance(d, EmulatedCamera)]
        self.clock = cams[0].clock if cams else VirtualClock()

    def enumerate_devices(self):
        return [d for d in self.devices if getattr(d, "plugged", True)]

    def get_device_descriptor(self, dev):
        cam = isinstance(dev, EmulatedCamera)
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200,
            bDeviceClass=0 if cam else dev.device_class, bDeviceSubClass=0, bDeviceProtocol=0,
            bMaxPacketSize0=64, idVendor=dev.p.id_vendor if cam else dev.id_vendor,
            idProduct=dev.p.id_product if cam else dev.id_product, bcdDevice=0x0100,
            iManufacturer=1 if cam else 0, iProduct=2 if cam else 0,
            iSerialNumber=3 if cam else 0, bNumConfigurations=1, bus=dev.bus,
            address=dev.address, port_number=1, port_numbers=(1,), speed=3,
        )

    def has_interface(self, dev) -> bool:
        return isinstance(dev, EmulatedCamera)

    def endpoints(self, dev):
        return ((BULK_IN, 2, dev.p.packet_size), (BULK_OUT, 2, dev.p.packet_size), (INTR_IN, 3, 8))

    def check(self, dev_handle) -> None:
        dev_handle._alive()

    def open_device(self, dev):
        if not getattr(dev, "plugged", True):
            raise usb.core.USBError("No such device", *_ENODEV)
        return dev

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        dev_handle._alive()
        if bmRequestType & 0x60 == 0x20:  # class request to the interface
            length = len(data) * data.itemsize if data is not None else 0
            out = None if bmRequestType & 0x80 else bytes(data or b"")
            result = dev_handle.class_request(bRequest, out, length)
            if isinstance(result, int):
                return result
            data[: len(result)] = type(data)(data.typecode, result[:length])
            return min(len(result), length)
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:  # GET_DESCRIPTOR string
            index = wValue & 0xFF
            payload = (struct.pack("<H", 0x0409) if index == 0
                       else dev_handle.strings()[index].encode("utf-16-le"))
            blob = bytes([2 + len(payload), 3]) + payload
            data[: len(blob)] = type(data)(data.typecode, blob[: len(data)])
            return min(len(blob), len(data))
        raise usb.core.USBError("Pipe error", *_EPIPE)

    def clear_halt(self, dev_handle, ep):
        dev_handle.clear_halt(ep)

    def reset_device(self, dev_handle):
        dev_handle._alive()


def emulated_backend(vendor: str | None, name: str | None = None, **camera_options):
    """A backend with one emulated camera (``vendor`` ``"canon"``/``"nikon"``), or none.

    ``vendor`` ``None`` gives a bus with only a hub (what ``tether list`` shows
    when no camera is found).
    """
    if vendor is None:
        return EmulatedBackend(OtherDevice())
    return EmulatedBackend(EmulatedCamera(personality(vendor, name), **camera_options))


__all__ = ["CANON", "NIKON", "EmulatedBackend", "EmulatedCamera", "Faults", "OtherDevice",
           "Personality", "emulated_backend"]
