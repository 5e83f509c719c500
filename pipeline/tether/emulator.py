"""An emulated PTP camera as a pyusb backend (``usb.backend.IBackend``), no monkey-patching.

``usb.core.find(backend=EmulatedBackend(EmulatedCamera(CANON)))`` gives a real
``usb.core.Device``; every byte goes through pyusb's endpoint and control
transfer code into this backend, which plays a Canon EOS or Nikon body: a
Still Image interface (bulk in/out, interrupt in), the PTP container protocol
with the zero-length-packet rule, the class requests, a focus motor with a
position, limits and per-size steps, live view, a shutter (bulb too), images
rendered at the motor's focus by :func:`pipeline.tether.scene.render_frame`,
events, and switchable faults (busy, refusal while exposing, stall, timeout,
unplug mid-transfer).
"""

from __future__ import annotations

import errno
import itertools
import struct
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import usb.backend
import usb.core

from pipeline.tether import canon, nikon
from pipeline.tether.codes import (
    CANON_DRIVE_FAR,
    CANON_EVF_PC,
    OC,
    RC,
    CanonDPC,
    CanonEC,
    CanonOC,
    CanonRC,
    ClassRequest,
    ContainerType,
    NikonEC,
    NikonOC,
    NikonRC,
)
from pipeline.tether.ptp import HEADER, Container, DeviceInfo, ObjectInfo, encode_container
from pipeline.tether.scene import encode_jpeg, encode_tiff16, render_frame

BULK_IN, BULK_OUT, INTR_IN = 0x81, 0x02, 0x83
_ENODEV = (-4, errno.ENODEV)  # LIBUSB_ERROR_NO_DEVICE
_EPIPE = (-9, errno.EPIPE)  # LIBUSB_ERROR_PIPE
_TIMEOUT = (-7, errno.ETIMEDOUT)  # LIBUSB_ERROR_TIMEOUT
_DATA_OUT_OPS = {CanonOC.SetDevicePropValueEx, OC.SetDevicePropValue}


@dataclass(frozen=True)
class Personality:
    """A camera model: USB ids, GetDeviceInfo contents, image format, motor steps."""

    vendor: str
    id_vendor: int
    id_product: int
    manufacturer: str
    model: str
    vendor_extension_id: int
    operations: tuple[int, ...]
    image_format: str  # "jpeg" or "tiff"
    steps_per_size: dict = field(default_factory=lambda: {1: 1})
    packet_size: int = 512


_COMMON_OPS = (OC.GetDeviceInfo, OC.OpenSession, OC.CloseSession, OC.GetObjectInfo,
               OC.GetObject, OC.GetPartialObject)
CANON = Personality(
    "canon", 0x04A9, 0x3199, "Canon Inc.", "Canon EOS (emulated)", 0x0000000B,
    (*_COMMON_OPS, *CanonOC), "jpeg", {1: 1, 2: 4, 3: 16},
)
NIKON = Personality(
    "nikon", 0x04B0, 0x0429, "Nikon Corporation", "Nikon DSLR (emulated)", 0x0000000A,
    (*_COMMON_OPS, *NikonOC), "tiff",
)


@dataclass
class Faults:
    """Faults to switch on. Counters are used up as they fire."""

    busy_responses: int = 0  # next N drive/capture/download commands answer DeviceBusy
    busy_ops: frozenset = frozenset({CanonOC.DriveLens, NikonOC.MfDrive, CanonOC.RemoteReleaseOn,
                                     NikonOC.InitiateCaptureRecInSdram, CanonOC.GetPartialObject,
                                     OC.GetPartialObject})
    refuse_drive_while_exposing: bool = True  # as real bodies do
    stall_on: int | None = None  # stall bulk-in on the next command with this opcode
    timeout_on: int | None = None  # never answer the next command with this opcode
    unplug_on_download: int | None = None  # vanish mid data phase of the k-th download (0-based)


class EmulatedCamera:
    """The device side: descriptors, wire protocol, PTP state machine, motor, shutter."""

    def __init__(
        self,
        personality: Personality = CANON,
        *,
        faults: Faults | None = None,
        position: int = 0,
        limits: tuple[int, int] = (0, 400),
        shutter: str = "normal",
        renderer=render_frame,
        bus: int = 1,
        address: int = 5,
    ) -> None:
        self.p = personality
        self.faults = faults or Faults()
        self.position = position
        self.limits = limits
        self.shutter = shutter  # "normal" or "bulb"
        self.renderer = renderer
        self.bus, self.address = bus, address
        self.plugged = True
        # PTP state
        self.session_open = False
        self.remote_mode = 0
        self.event_mode = 0
        self.properties: dict[int, int] = {CanonDPC.EVFOutputDevice: 0}
        self.live_view = False
        self.exposing = False
        self._exposure: list[tuple[float, int]] = []
        self.objects: dict[int, tuple[str, bytes]] = {}
        self._next_handle = 1
        self._events: list = []
        self._ready_busy = 0
        self._ready_result = RC.OK
        # logs the tests compare against
        self.motor_log: list[tuple[float, int]] = [(time.monotonic(), position)]
        self.shots: list[tuple[int, int]] = []  # (handle, motor position at the shot)
        self.transactions: list[tuple[int, int, tuple]] = []  # (tid, opcode, params)
        self.busy_given = 0
        self.cancelled: list[int] = []
        self.halts_cleared: list[int] = []
        self.zlps_received = 0
        self.downloads_started = 0
        # wire state
        self._in = bytearray()
        self._command: Container | None = None
        self._expect_zlp = False
        self._out: list[bytes] = []
        self._out_pos = 0
        self._zlp_due = False
        self._stalled = False
        self._hanging: int | None = None
        self._unplug_armed = False

    @property
    def evf_on(self) -> bool:
        return self.properties[CanonDPC.EVFOutputDevice] == CANON_EVF_PC

    def unplug(self) -> None:
        self.plugged = False

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
        if len(self._in) >= HEADER.size:
            length = HEADER.unpack_from(self._in)[0]
            if len(self._in) >= length:
                blob, self._in = bytes(self._in[:length]), self._in[length:]
                self._expect_zlp = length % self.p.packet_size == 0
                self._container_in(blob)
        return len(data)

    def _container_in(self, blob: bytes) -> None:
        length, ctype, code, tid = HEADER.unpack_from(blob)
        if ctype == ContainerType.COMMAND:
            count = (length - HEADER.size) // 4
            params = struct.unpack_from(f"<{count}I", blob, HEADER.size)
            self._command = Container(ContainerType.COMMAND, code, tid, params)
            if code not in _DATA_OUT_OPS:
                self._run(self._command, None)
        elif ctype == ContainerType.DATA and self._command is not None:
            self._run(self._command, blob[HEADER.size :])

    # --- wire level: bulk in ----------------------------------------------------------------

    def host_read(self, size: int) -> bytes:
        self._alive()
        if self._stalled:
            raise usb.core.USBError("Pipe error", *_EPIPE)
        if self._hanging is not None or not (self._out or self._zlp_due):
            raise usb.core.USBTimeoutError("Operation timed out", *_TIMEOUT)
        if size % self.p.packet_size:
            raise AssertionError(f"bulk-in read of {size} bytes is not a multiple of the packet")
        if not self._out:  # only the ZLP of the previous transfer is left
            self._zlp_due = False
            return b""
        current = self._out[0]
        n = min(size, len(current) - self._out_pos)
        if self._unplug_armed and current[4:6] == b"\x02\x00":
            n = min(n, max(self.p.packet_size, len(current) // 2 // self.p.packet_size
                           * self.p.packet_size))
            self._unplug_armed = False
            self.plugged = False
        chunk = current[self._out_pos : self._out_pos + n]
        self._out_pos += n
        if self._out_pos == len(current):
            self._out.pop(0)
            self._out_pos = 0
            # a read that ended exactly on the last full packet leaves the ZLP for the next read
            self._zlp_due = len(current) % self.p.packet_size == 0 and n == size
        return chunk

    def _alive(self) -> None:
        if not self.plugged:
            raise usb.core.USBError("No such device (it may have been disconnected)", *_ENODEV)

    # --- class requests ---------------------------------------------------------------------

    def class_request(self, request: int, data: bytes | None, length: int) -> bytes | int:
        self._alive()
        if request == ClassRequest.CANCEL:
            _code, tid = struct.unpack("<HI", bytes(data))
            self.cancelled.append(tid)
            self._hanging = None
            self._out, self._out_pos, self._zlp_due, self._command = [], 0, False, None
            return len(data)
        if request == ClassRequest.DEVICE_RESET:
            self.__init__(self.p, faults=self.faults, position=self.position, limits=self.limits,
                          shutter=self.shutter, renderer=self.renderer)
            return 0
        if request == ClassRequest.GET_DEVICE_STATUS:
            if self._stalled:
                return struct.pack("<HHI", 8, RC.IncompleteTransfer, BULK_IN)
            code = RC.DeviceBusy if self._hanging is not None else RC.OK
            return struct.pack("<HH", 4, code)
        raise usb.core.USBError("Pipe error", *_EPIPE)

    def clear_halt(self, ep: int) -> None:
        self._alive()
        self.halts_cleared.append(ep)
        if ep == BULK_IN:
            self._stalled = False
            self._out, self._out_pos, self._zlp_due = [], 0, False

    # --- PTP --------------------------------------------------------------------------------

    def _run(self, cmd: Container, data_out: bytes | None) -> None:
        self.transactions.append((cmd.transaction_id, cmd.code, cmd.params))
        f = self.faults
        if f.timeout_on == cmd.code:
            f.timeout_on = None
            self._hanging = cmd.transaction_id
            return
        if f.stall_on == cmd.code:
            f.stall_on = None
            self._stalled = True
            return
        if f.busy_responses and cmd.code in f.busy_ops and self.session_open:
            f.busy_responses -= 1
            self.busy_given += 1
            code, params, data = RC.DeviceBusy, (), None
        else:
            code, params, data = self._operate(cmd.code, cmd.params, data_out)
        tid = cmd.transaction_id
        if data is not None:
            self._out.append(encode_container(Container(ContainerType.DATA, cmd.code, tid,
                                                        payload=data)))
        self._out.append(encode_container(Container(ContainerType.RESPONSE, code, tid, params)))

    def _operate(self, op: int, params: tuple, data_out: bytes | None):
        """(response code, response params, data-in payload or None)."""
        if op not in self.p.operations:
            return RC.OperationNotSupported, (), None
        if op == OC.GetDeviceInfo:
            return RC.OK, (), self.device_info().to_bytes()
        if op == OC.OpenSession:
            if self.session_open:
                return RC.SessionAlreadyOpened, (), None
            self.session_open = True
            return RC.OK, (), None
        if not self.session_open:
            return RC.SessionNotOpen, (), None
        if op == OC.CloseSession:
            self.session_open = False
            return RC.OK, (), None
        vendor_op = getattr(self, f"_{self.p.vendor}_{op:04x}", None)
        if vendor_op is not None:
            return vendor_op(*params, data=data_out)
        if op in (OC.GetPartialObject, CanonOC.GetPartialObject):
            return self._partial(*params)
        if op == OC.GetObjectInfo:
            name, blob = self.objects.get(params[0], (None, b""))
            if name is None:
                return RC.InvalidObjectHandle, (), None
            fmt = 0x380D if name.endswith(".TIF") else 0x3801
            return RC.OK, (), ObjectInfo(len(blob), name, fmt).to_bytes()
        return RC.ParameterNotSupported, (), None

    def device_info(self) -> DeviceInfo:
        return DeviceInfo(
            vendor_extension_id=self.p.vendor_extension_id, manufacturer=self.p.manufacturer,
            model=self.p.model, operations=self.p.operations, serial_number="EMU0001",
        )

    def _partial(self, handle=0, offset=0, length=0, *_):
        if handle not in self.objects:
            return RC.InvalidObjectHandle, (), None
        blob = self.objects[handle][1]
        if offset == 0:
            if self.faults.unplug_on_download == self.downloads_started:
                self._unplug_armed = True
            self.downloads_started += 1
        chunk = blob[offset : offset + length]
        return RC.OK, (len(chunk),), chunk

    def _move(self, steps: int) -> bool:
        """Drive the motor; False if it stopped at a limit."""
        lo, hi = self.limits
        target = self.position + steps
        self.position = min(max(target, lo), hi)
        now = time.monotonic()
        if self.exposing:
            self._exposure.append((now, self.position))
        self.motor_log.append((now, self.position))
        return self.position == target

    def _open_shutter(self) -> None:
        self.exposing = True
        self._exposure = [(time.monotonic(), self.position)]

    def _close_shutter(self) -> int:
        """End the exposure: render (time-weighted over motor positions), store; its handle."""
        self.exposing = False
        end = time.monotonic()
        marks = [*self._exposure, (end, self.position)]
        dwell = np.array([max(b[0] - a[0], 0.0) for a, b in itertools.pairwise(marks)])
        positions = [pos for _t, pos in marks[:-1]]
        if len(set(positions)) == 1 or dwell.sum() <= 0:
            image = self.renderer(positions[0])
        else:
            image = sum(w * self.renderer(pos) for w, pos in zip(dwell / dwell.sum(), positions))
        handle = self._next_handle
        self._next_handle += 1
        if self.p.image_format == "jpeg":
            name, blob = f"IMG_{handle:04d}.JPG", encode_jpeg(image)
        else:
            name, blob = f"DSC_{handle:04d}.TIF", encode_tiff16(image)
        self.objects[handle] = (name, blob)
        self.shots.append((handle, self.position))
        return handle

    # --- Canon EOS operations (method name: _canon_<opcode hex>) ----------------------------

    def _canon_9114(self, mode=0, *_, data=None):  # SetRemoteMode
        self.remote_mode = mode
        return RC.OK, (), None

    def _canon_9115(self, mode=0, *_, data=None):  # SetEventMode
        self.event_mode = mode
        return RC.OK, (), None

    def _canon_9110(self, *_, data=None):  # SetDevicePropValueEx
        _size, prop, value = struct.unpack_from("<III", data)
        self.properties[prop] = value
        self._events.append(canon.encode_event(CanonEC.PropValueChanged, (prop, value)))
        return RC.OK, (), None

    def _canon_9116(self, *_, data=None):  # GetEvent
        records, self._events = self._events, []
        return RC.OK, (), b"".join(records) + canon.EVENT_TERMINATOR

    def _canon_9155(self, code=0, *_, data=None):  # DriveLens
        if self.exposing and self.faults.refuse_drive_while_exposing:
            return CanonRC.OperationRefused, (), None
        if not self.evf_on:
            return CanonRC.OperationRefused, (), None
        size = code & 0x3
        if size not in self.p.steps_per_size:
            return RC.InvalidParameter, (), None
        steps = self.p.steps_per_size[size]
        self._move(steps if code & CANON_DRIVE_FAR else -steps)  # EOS stops silently at a limit
        return RC.OK, (), None

    def _canon_9128(self, press=0, *_, data=None):  # RemoteReleaseOn
        if press & 2 and not self.exposing:
            self._open_shutter()
            self._events.append(canon.encode_event(CanonEC.CameraStatusChanged, (1,)))
        return RC.OK, (), None

    def _canon_9129(self, press=0, *_, data=None):  # RemoteReleaseOff
        if press & 2 and self.exposing:
            handle = self._close_shutter()
            name, blob = self.objects[handle]
            self._events += [
                canon.encode_event(CanonEC.CameraStatusChanged, (0,)),
                canon.object_added_record(handle, len(blob), name),
            ]
        return RC.OK, (), None

    def _canon_9117(self, handle=0, *_, data=None):  # TransferComplete
        return (RC.OK if self.objects.pop(handle, None) else RC.InvalidObjectHandle), (), None

    # --- Nikon operations (method name: _nikon_<opcode hex>) --------------------------------

    def _nikon_9201(self, *_, data=None):  # StartLiveView
        self.live_view = True
        self._ready_busy = 1
        return RC.OK, (), None

    def _nikon_9202(self, *_, data=None):  # EndLiveView
        self.live_view = False
        return RC.OK, (), None

    def _nikon_90c8(self, *_, data=None):  # DeviceReady
        if self._ready_busy:
            self._ready_busy -= 1
            return RC.DeviceBusy, (), None
        result, self._ready_result = self._ready_result, RC.OK
        return result, (), None

    def _nikon_9204(self, direction=0, amount=0, *_, data=None):  # MfDrive
        if not self.live_view or (self.exposing and self.faults.refuse_drive_while_exposing):
            return NikonRC.NotLiveView, (), None
        if direction not in (1, 2):
            return RC.InvalidParameter, (), None
        if amount < 1:
            self._ready_result = NikonRC.MfDriveStepInsufficiency
        elif not self._move(amount if direction == 2 else -amount):
            self._ready_result = NikonRC.MfDriveStepEnd
        self._ready_busy = 1
        return RC.OK, (), None

    def _nikon_90c0(self, *_, data=None):  # InitiateCaptureRecInSdram
        self._open_shutter()
        if self.shutter != "bulb":
            self._nikon_captured()
        return RC.OK, (), None

    def _nikon_920c(self, *_, data=None):  # TerminateCapture
        if self.exposing:
            self._nikon_captured()
        return RC.OK, (), None

    def _nikon_captured(self) -> None:
        handle = self._close_shutter()
        self._events.append((NikonEC.ObjectAddedInSDRAM, handle))
        self._ready_busy = 2

    def _nikon_90c7(self, *_, data=None):  # GetEvent
        events, self._events = self._events, []
        return RC.OK, (), nikon.encode_events(events)

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


class EmulatedBackend(usb.backend.IBackend):
    """A pyusb backend whose devices are :class:`EmulatedCamera` (and :class:`OtherDevice`)."""

    def __init__(self, *devices) -> None:
        super().__init__()
        self.devices = list(devices)

    def enumerate_devices(self):
        return [d for d in self.devices if getattr(d, "plugged", True)]

    def get_parent(self, dev):
        return None

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

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(f"invalid configuration index {config}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=39,
            bNumInterfaces=1 if isinstance(dev, EmulatedCamera) else 0, bConfigurationValue=1,
            iConfiguration=0, bmAttributes=0xC0, bMaxPower=50, extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev, intf, alt, config):
        if not isinstance(dev, EmulatedCamera) or intf != 0 or alt != 0:
            raise IndexError(f"invalid interface {intf}/{alt}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
            bNumEndpoints=3, bInterfaceClass=6, bInterfaceSubClass=1, bInterfaceProtocol=1,
            iInterface=0, extra_descriptors=[],
        )

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        address, attributes, size = ((BULK_IN, 2, dev.p.packet_size),
                                     (BULK_OUT, 2, dev.p.packet_size), (INTR_IN, 3, 8))[ep]
        return SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=address, bmAttributes=attributes,
            wMaxPacketSize=size, bInterval=0 if attributes == 2 else 10, bRefresh=0,
            bSynchAddress=0, extra_descriptors=[],
        )

    def open_device(self, dev):
        if not getattr(dev, "plugged", True):
            raise usb.core.USBError("No such device", *_ENODEV)
        return dev

    def close_device(self, dev_handle):
        return None

    def set_configuration(self, dev_handle, config_value):
        dev_handle._alive()

    def get_configuration(self, dev_handle):
        return 1

    def claim_interface(self, dev_handle, intf):
        dev_handle._alive()

    def release_interface(self, dev_handle, intf):
        dev_handle._alive()

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        return dev_handle.host_write(bytes(data))

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        chunk = dev_handle.host_read(len(buff) * buff.itemsize)
        buff[: len(chunk)] = type(buff)(buff.typecode, chunk)
        return len(chunk)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        dev_handle._alive()
        raise usb.core.USBTimeoutError("Operation timed out", *_TIMEOUT)

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


def emulated_backend(vendor: str, **camera_options) -> EmulatedBackend:
    """A backend with one emulated ``"canon"`` or ``"nikon"`` camera (for ``--emulate``)."""
    personality = {"canon": CANON, "nikon": NIKON}[vendor]
    return EmulatedBackend(EmulatedCamera(personality, **camera_options))
