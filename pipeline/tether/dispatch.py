"""Dispatch to the vendor driver of an open session.

Opcodes collide between vendors (0x9107 is Canon EOS GetPartialObject, 0xC101 is
two different events), so the driver is chosen from the GetDeviceInfo vendor
extension id (or the USB vendor id), never from the operations alone.
"""

from __future__ import annotations

from pipeline.tether.base import FocusCamera
from pipeline.tether.canon import CanonEOS
from pipeline.tether.nikon import Nikon
from pipeline.tether.session import PtpSession, UnsupportedCamera

DRIVERS = {"canon": CanonEOS, "nikon": Nikon}


def camera_for(session: PtpSession, **options) -> FocusCamera:
    """The vendor driver for an open session (Canon EOS or Nikon).

    Parameters
    ----------
    session : PtpSession
        Open session (its ``vendor`` was set from GetDeviceInfo).
    **options
        Passed to the driver (``drive_size``, ``drive_pace_s``).
    """
    if session.vendor not in DRIVERS:
        model = session.device_info.model if session.device_info else "camera"
        raise UnsupportedCamera(
            f"{model}: no focus-drive support for vendor {session.vendor or 'unknown'} "
            "(supported: Canon EOS, Nikon)"
        )
    return DRIVERS[session.vendor](session, **options)
