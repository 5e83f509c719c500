"""What a capture flow needs from a camera, and dispatch to the vendor driver.

Opcodes collide between vendors (0x9107 is Canon EOS GetPartialObject, 0xC101 is
two different events), so the driver is chosen from the GetDeviceInfo vendor
extension id (or the USB vendor id), never from the operations alone.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from pipeline.errors import TetherError
from pipeline.tether.ptp import iter_chunks
from pipeline.tether.session import PtpError, PtpSession, UnsupportedCamera

log = logging.getLogger(__name__)

CHUNK_BYTES = 1 << 20


class EndStop(TetherError):
    """The focus drive reached the end of its travel."""


class DriveRefused(PtpError):
    """The camera refused to drive the focus (e.g. while the shutter is open)."""


@dataclass(frozen=True)
class CapturedObject:
    handle: int
    size: int
    filename: str


@dataclass
class FocusCamera:
    """Base class of the vendor drivers: focus drive, capture, download, safe state.

    Focus positions count drive steps from where the flow started (+ towards far).
    """

    session: PtpSession
    drive_size: int = 1
    position: int = 0
    drive_log: list[tuple[float, int]] = field(default_factory=list)

    # class constants of each driver (not dataclass fields: no annotations)
    vendor = ""
    stack_ops = ()
    bulb_ops = ()
    refusal_codes = ()
    event_timeout_s = 10.0

    def __post_init__(self) -> None:
        """Drivers validate their options and set up their state here."""

    def check_supported(self, *, bulb: bool = False) -> None:
        self.session.require(self.stack_ops, "capture a focal stack")
        if bulb:
            self.session.require(self.bulb_ops, "expose in bulb while driving the focus")

    def start(self) -> None:
        """Remote control and live view on (needed before driving the focus)."""
        raise NotImplementedError

    def drive(self, steps: int) -> None:
        """Move the focus by ``steps`` (signed); updates :attr:`position` and the drive log."""
        if steps:
            self._drive(steps)
            self.position += steps
            self.drive_log.append((time.monotonic(), steps))

    def _drive(self, steps: int) -> None:
        raise NotImplementedError

    def capture(self) -> CapturedObject:
        raise NotImplementedError

    def capture_bulb(self, exposure_s: float) -> CapturedObject:
        """A bulb exposure of ``exposure_s`` seconds without focus motion."""
        self.open_exposure()
        time.sleep(exposure_s)
        return self.close_exposure()

    def open_exposure(self) -> None:
        raise NotImplementedError

    def close_exposure(self) -> CapturedObject:
        raise NotImplementedError

    def download(self, obj: CapturedObject, *, chunk: int = CHUNK_BYTES) -> bytes:
        """The object's bytes, fetched with GetPartialObject in ``chunk``-byte pieces."""
        parts = [self._partial(obj, offset, length) for offset, length in iter_chunks(obj.size,
                                                                                     chunk)]
        data = b"".join(parts)
        if len(data) != obj.size:
            raise TetherError(f"{obj.filename}: downloaded {len(data)} of {obj.size} bytes")
        self._download_done(obj)
        return data

    def _partial(self, obj: CapturedObject, offset: int, length: int) -> bytes:
        raise NotImplementedError

    def _download_done(self, obj: CapturedObject) -> None:
        """Vendor hook after a download (Canon: TransferComplete)."""

    def safe_state(self) -> None:
        """Live view off, remote mode off. Never raises: the camera may be gone."""
        raise NotImplementedError

    def _quietly(self, what: str, func, *args) -> None:
        try:
            func(*args)
        except TetherError as err:
            log.warning("could not %s while restoring the camera: %s", what, err)

    def _poll(self, what: str, step):
        """Call ``step()`` until it returns something, with backoff, up to ``event_timeout_s``."""
        deadline = time.monotonic() + self.event_timeout_s
        delay = self.session.backoff_s
        while True:
            result = step()
            if result is not None:
                return result
            if time.monotonic() > deadline:
                raise TetherError(f"{what}: nothing after {self.event_timeout_s:.0f} s")
            self.session.sleep(delay)
            delay = min(2 * delay, self.session.max_backoff_s)


def camera_for(session: PtpSession, **options) -> FocusCamera:
    """The vendor driver for an open session (Canon EOS or Nikon)."""
    from pipeline.tether.canon import CanonEOS
    from pipeline.tether.nikon import Nikon

    drivers = {"canon": CanonEOS, "nikon": Nikon}
    if session.vendor not in drivers:
        model = session.device_info.model if session.device_info else "camera"
        raise UnsupportedCamera(
            f"{model}: no focus-drive support for vendor {session.vendor or 'unknown'} "
            "(supported: Canon EOS, Nikon)"
        )
    return drivers[session.vendor](session, **options)
