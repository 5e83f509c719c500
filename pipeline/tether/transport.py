"""USB transport for PTP: Still Image device discovery, bulk/interrupt I/O, class requests.

pyusb does the USB work; the default backend is the libusb-1.0 shipped by the
``libusb-package`` wheel, so ``pip install`` alone is enough. Any
``usb.backend.IBackend`` can be passed instead (the emulator is one).
"""

from __future__ import annotations

import errno
import logging
import struct
from dataclasses import dataclass

import usb.core
import usb.util

from pipeline.errors import TetherError
from pipeline.tether.codes import (
    EC,
    RC,
    STILL_IMAGE_CLASS,
    USB_VENDOR_IDS,
    ClassRequest,
)
from pipeline.tether.ptp import (
    Container,
    container_length,
    decode_container,
    encode_container,
    read_sizes,
    split_transfers,
)

log = logging.getLogger(__name__)

MAX_TRANSFER = 512 * 1024  # bytes per bulk transfer request (a multiple of every packet size)
_LIBUSB_ERROR_NO_DEVICE = -4
_LIBUSB_ERROR_PIPE = -9
_CTRL_OUT = usb.util.CTRL_OUT | usb.util.CTRL_TYPE_CLASS | usb.util.CTRL_RECIPIENT_INTERFACE
_CTRL_IN = usb.util.CTRL_IN | usb.util.CTRL_TYPE_CLASS | usb.util.CTRL_RECIPIENT_INTERFACE


class TransportTimeout(TetherError):
    """A USB transfer did not complete in time."""


class DeviceGone(TetherError):
    """The camera was unplugged or switched off."""


class EndpointStalled(TetherError):
    """The camera stalled an endpoint (it aborted the transaction)."""


def default_backend():
    """The libusb-1.0 backend bundled by ``libusb-package`` (no system libusb needed)."""
    import libusb_package

    backend = libusb_package.get_libusb1_backend()
    if backend is None:
        raise TetherError("libusb-package could not load its libusb-1.0 library")
    return backend


def _is_still_image(intf) -> bool:
    return (intf.bInterfaceClass, intf.bInterfaceSubClass, intf.bInterfaceProtocol) == (
        STILL_IMAGE_CLASS
    )


def _still_image_interface(dev):
    for cfg in dev:
        for intf in cfg:
            if _is_still_image(intf):
                return cfg, intf
    return None, None


def find_cameras(backend=None) -> tuple[list, list[str]]:
    """Still Image class (6/1/1) devices, and a one-line description of every device seen."""
    backend = backend if backend is not None else default_backend()
    try:
        devices = list(usb.core.find(find_all=True, backend=backend))
    except usb.core.USBError as err:
        raise TetherError(f"cannot enumerate USB devices: {err}") from err
    cameras, seen = [], []
    for dev in devices:
        vendor = USB_VENDOR_IDS.get(dev.idVendor, "unknown vendor")
        is_camera = _still_image_interface(dev)[1] is not None
        seen.append(
            f"{dev.idVendor:04x}:{dev.idProduct:04x} ({vendor}, "
            f"{'Still Image class' if is_camera else f'class {dev.bDeviceClass}'})"
        )
        if is_camera:
            cameras.append(dev)
    return cameras, seen


def no_camera_message(seen: list[str]) -> str:
    """One line: what was seen on the bus and the usual reasons no camera shows up."""
    listing = "; ".join(seen) if seen else "no USB devices at all (no permission to list them?)"
    return (
        f"no PTP camera (USB Still Image class 6/1/1) found; seen: {listing}. "
        "Switch the camera on and set its USB mode to PTP (not MTP/mass storage), close "
        "gvfs/gphoto2 programs that hold it (gio mount -s gphoto2), and check permissions "
        "(a udev rule, see README 'Real cameras')"
    )


@dataclass(frozen=True)
class Endpoints:
    bulk_in: object
    bulk_out: object
    interrupt: object | None


class UsbTransport:
    """PTP containers over one Still Image interface (bulk-out, bulk-in, interrupt-in).

    Parameters
    ----------
    device : usb.core.Device
        A device with a Still Image class interface (see :func:`find_cameras`).
    timeout_ms : int
        Default time limit of one bulk transfer.
    """

    def __init__(self, device, *, timeout_ms: int = 5000) -> None:
        self.device = device
        self.timeout_ms = timeout_ms
        self._pending = b""  # bytes of the next container read ahead while looking for a ZLP
        cfg, intf = _still_image_interface(device)
        if intf is None:
            raise TetherError(
                f"USB device {device.idVendor:04x}:{device.idProduct:04x} has no "
                "Still Image (6/1/1) interface"
            )
        self.interface_number = intf.bInterfaceNumber
        try:
            if device.is_kernel_driver_active(self.interface_number):
                device.detach_kernel_driver(self.interface_number)
        except NotImplementedError:
            log.debug("backend cannot query kernel drivers; continuing")
        except usb.core.USBError as err:
            raise self._wrap(err, "detach the kernel driver (is gphoto2/gvfs using it?)") from err
        try:
            device.set_configuration(cfg.bConfigurationValue)
            usb.util.claim_interface(device, self.interface_number)
        except usb.core.USBError as err:
            raise self._wrap(err, "claim the camera's USB interface") from err

        def endpoint(direction, kind):
            return usb.util.find_descriptor(
                intf,
                custom_match=lambda e: usb.util.endpoint_direction(e.bEndpointAddress) == direction
                and usb.util.endpoint_type(e.bmAttributes) == kind,
            )

        self.endpoints = Endpoints(
            endpoint(usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_BULK),
            endpoint(usb.util.ENDPOINT_OUT, usb.util.ENDPOINT_TYPE_BULK),
            endpoint(usb.util.ENDPOINT_IN, usb.util.ENDPOINT_TYPE_INTR),
        )
        if self.endpoints.bulk_in is None or self.endpoints.bulk_out is None:
            raise TetherError("the Still Image interface lacks a bulk-in or bulk-out endpoint")
        self.packet_in = self.endpoints.bulk_in.wMaxPacketSize
        self.packet_out = self.endpoints.bulk_out.wMaxPacketSize

    # --- errors ---------------------------------------------------------------------------

    @staticmethod
    def _wrap(err: usb.core.USBError, doing: str) -> TetherError:
        if isinstance(err, usb.core.USBTimeoutError):
            return TransportTimeout(f"USB timeout while trying to {doing}")
        if err.errno == errno.ENODEV or err.backend_error_code == _LIBUSB_ERROR_NO_DEVICE:
            return DeviceGone(f"camera disconnected while trying to {doing}")
        if err.errno == errno.EPIPE or err.backend_error_code == _LIBUSB_ERROR_PIPE:
            return EndpointStalled(f"camera stalled the endpoint while trying to {doing}")
        if err.errno == errno.EACCES:
            return TetherError(
                f"permission denied while trying to {doing}: add a udev rule for the camera "
                "(see README, 'Real cameras')"
            )
        return TetherError(f"USB error while trying to {doing}: {err}")

    # --- containers -----------------------------------------------------------------------

    def send(self, container: Container, *, timeout_ms: int | None = None) -> None:
        """Write one container as one transfer (in ``MAX_TRANSFER`` pieces, ZLP if due)."""
        blob = encode_container(container)
        timeout = timeout_ms or self.timeout_ms
        try:
            for chunk in split_transfers(blob, self.packet_out, MAX_TRANSFER):
                self.endpoints.bulk_out.write(chunk, timeout)
        except usb.core.USBError as err:
            raise self._wrap(err, f"send a {container.type.name.lower()} container") from err

    def receive(self, *, timeout_ms: int | None = None) -> Container:
        """Read one container from bulk-in.

        A container may span several transfers; a device that omits the
        zero-length packet after a container ending on a packet boundary runs
        the next container into the same read, so bytes past the announced
        length are kept for the next call. A stray zero-length packet at the
        start of a read (the ZLP ending the previous container) is skipped.
        """
        timeout = timeout_ms or self.timeout_ms
        try:
            blob = self._pending
            self._pending = b""
            for _ in range(3):
                if blob:
                    break
                blob = self._read(MAX_TRANSFER, timeout)  # b"": a stray ZLP, read again
            length = container_length(blob)
            parts, got = [blob], len(blob)
            for size in read_sizes(length - got, self.packet_in, MAX_TRANSFER):
                chunk = self._read(size, timeout)
                parts.append(chunk)
                got += len(chunk)
                if len(chunk) < size:
                    break
            if got < length:
                raise TetherError(f"camera sent {got} bytes of a {length}-byte container")
            whole = b"".join(parts)
            self._pending = whole[length:]
        except usb.core.USBError as err:
            raise self._wrap(err, "receive from the camera") from err
        return decode_container(whole[:length])

    def _read(self, size: int, timeout: int) -> bytes:
        return bytes(self.endpoints.bulk_in.read(size, timeout))

    # --- class requests (USB Still Image class, Sec. 5.2) ---------------------------------

    def cancel(self, transaction_id: int) -> None:
        """Cancel request 0x64: abort the transaction ``transaction_id``."""
        data = struct.pack("<HI", EC.CancelTransaction, transaction_id)
        self._control_out(ClassRequest.CANCEL, data, "cancel the transaction")
        self._pending = b""

    def reset(self) -> None:
        """Device reset request 0x66: back to the idle state, session closed."""
        self._control_out(ClassRequest.DEVICE_RESET, None, "reset the camera")
        self._pending = b""

    def device_status(self) -> tuple[int, tuple[int, ...]]:
        """Get device status request 0x67: (response code, stalled endpoint addresses)."""
        try:
            raw = bytes(
                self.device.ctrl_transfer(
                    _CTRL_IN, ClassRequest.GET_DEVICE_STATUS, 0, self.interface_number, 64,
                    self.timeout_ms,
                )
            )
        except usb.core.USBError as err:
            raise self._wrap(err, "get the device status") from err
        if len(raw) < 4:
            return RC.GeneralError, ()
        length, code = struct.unpack_from("<HH", raw)
        count = max(0, (min(length, len(raw)) - 4) // 4)
        return code, struct.unpack_from(f"<{count}I", raw, 4)

    def clear_halts(self, addresses: tuple[int, ...] | None = None) -> None:
        """Clear a stall on the given (default: both bulk) endpoints."""
        if addresses is None:
            addresses = (
                self.endpoints.bulk_in.bEndpointAddress,
                self.endpoints.bulk_out.bEndpointAddress,
            )
        try:
            for address in addresses:
                self.device.clear_halt(address)
        except usb.core.USBError as err:
            raise self._wrap(err, "clear a stalled endpoint") from err
        self._pending = b""

    def _control_out(self, request: int, data: bytes | None, doing: str) -> None:
        try:
            self.device.ctrl_transfer(
                _CTRL_OUT, request, 0, self.interface_number, data, self.timeout_ms
            )
        except usb.core.USBError as err:
            raise self._wrap(err, doing) from err

    def close(self) -> None:
        """Release the interface and the device handle (safe to call twice)."""
        try:
            usb.util.release_interface(self.device, self.interface_number)
        except usb.core.USBError as err:
            log.debug("releasing the interface failed: %s", err)
        usb.util.dispose_resources(self.device)
