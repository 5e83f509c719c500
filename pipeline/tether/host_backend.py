"""The pyusb backend side shared by the cameras that live in this process (the emulated
and the replayed camera): a PTP still-image interface (class 6) with a bulk-in, a
bulk-out and an interrupt endpoint, whose bulk pipes go to the device object's
``host_write``/``host_read``. Subclasses say which devices exist and what their
descriptors and class requests are."""

from __future__ import annotations

import errno
from types import SimpleNamespace

import usb.backend
import usb.core

TIMEOUT = (-7, errno.ETIMEDOUT)  # LIBUSB_ERROR_TIMEOUT


class HostBackend(usb.backend.IBackend):
    """Descriptors and transfers of an in-process PTP camera (see the module docstring).

    Subclasses implement ``enumerate_devices``, ``get_device_descriptor``,
    ``ctrl_transfer`` and :meth:`endpoints`; :meth:`check` runs before every
    operation on an open device (an unplugged emulated camera raises there).
    """

    def endpoints(self, dev) -> tuple[tuple[int, int, int], ...]:
        """(address, attributes, max packet size) of the bulk-in, bulk-out, interrupt pipes."""
        raise NotImplementedError

    def has_interface(self, dev) -> bool:
        """Whether ``dev`` has the PTP interface (another USB device on the bus has none)."""
        return True

    def check(self, dev_handle) -> None:
        """Raise a pyusb error if the device can no longer be used."""

    def get_parent(self, dev):
        return None

    def get_configuration_descriptor(self, dev, config):
        if config != 0:
            raise IndexError(f"invalid configuration index {config}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=39,
            bNumInterfaces=1 if self.has_interface(dev) else 0, bConfigurationValue=1,
            iConfiguration=0, bmAttributes=0xC0, bMaxPower=50, extra_descriptors=[],
        )

    def get_interface_descriptor(self, dev, intf, alt, config):
        if not self.has_interface(dev) or intf != 0 or alt != 0:
            raise IndexError(f"invalid interface {intf}/{alt}")
        return SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
            bNumEndpoints=3, bInterfaceClass=6, bInterfaceSubClass=1, bInterfaceProtocol=1,
            iInterface=0, extra_descriptors=[],
        )

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        address, attributes, size = self.endpoints(dev)[ep]
        return SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=address, bmAttributes=attributes,
            wMaxPacketSize=size, bInterval=0 if attributes == 2 else 10, bRefresh=0,
            bSynchAddress=0, extra_descriptors=[],
        )

    def open_device(self, dev):
        return dev

    def close_device(self, dev_handle):
        return None

    def set_configuration(self, dev_handle, config_value):
        self.check(dev_handle)

    def get_configuration(self, dev_handle):
        return 1

    def claim_interface(self, dev_handle, intf):
        self.check(dev_handle)

    def release_interface(self, dev_handle, intf):
        self.check(dev_handle)

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        return dev_handle.host_write(bytes(data))

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        chunk = dev_handle.host_read(len(buff) * buff.itemsize)
        buff[: len(chunk)] = type(buff)(buff.typecode, chunk)
        return len(chunk)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        self.check(dev_handle)
        raise usb.core.USBTimeoutError("Operation timed out", *TIMEOUT)
