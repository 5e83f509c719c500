"""What a capture flow needs from a camera: the driver interface and its exceptions.

The vendor drivers (:mod:`pipeline.tether.canon`, :mod:`pipeline.tether.nikon`)
subclass :class:`FocusCamera`; :func:`pipeline.tether.dispatch.camera_for`
picks one. This module imports neither, so there is no import cycle.
"""

from __future__ import annotations

import logging
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


class LensAtManual(TetherError):
    """The lens focus switch is at MF: the body ignores focus-drive commands."""


@dataclass(frozen=True)
class CapturedObject:
    """A captured image on the camera.

    Attributes
    ----------
    handle : int
        PTP object handle.
    size : int
        Bytes.
    filename : str
        The camera's file name (its suffix names the format).
    transfer : bool
        The camera holds it in RAM for the host (Canon CaptureDestination = PC):
        it is released with TransferComplete after the download.
    """

    handle: int
    size: int
    filename: str
    transfer: bool = False


@dataclass
class FocusCamera:
    """Base class of the vendor drivers: focus drive, capture, download, safe state.

    Focus positions count drive steps from where the flow started (+ towards far);
    :attr:`position` only counts drives the camera acknowledged.

    Parameters
    ----------
    session : PtpSession
        An open session; its clock times every wait.
    drive_size : int
        Vendor step size (Canon DriveLens 1-3; Nikon only 1).
    drive_pace_s : float, optional
        Least time between two drive commands (default: the driver's per-size value).
    """

    session: PtpSession
    drive_size: int = 1
    drive_pace_s: float | None = None
    position: int = 0
    drive_log: list[tuple[float, int]] = field(default_factory=list)

    # class constants of each driver (not dataclass fields: no annotations)
    vendor = ""
    stack_ops = ()
    bulb_ops = ()
    sweep_refusal = ""  # non-empty: why no body of this vendor can sweep, whatever it lists
    refusal_codes = ()
    event_timeout_s = 90.0  # libgphoto2 waits 90 s (long exposures, noise reduction)

    def __post_init__(self) -> None:
        self.exposing = False
        self.setup()

    def setup(self) -> None:
        """Drivers validate their options and set up their state here."""

    @property
    def clock(self):
        """The session's clock (``now()``, ``sleep()``)."""
        return self.session.clock

    @classmethod
    def required_operations(cls, *, bulb: bool = False) -> tuple[int, ...]:
        """The operations the stack flow (``bulb=False``) or the sweep flow needs, in order."""
        return tuple(dict.fromkeys((*cls.stack_ops, *cls.bulb_ops))) if bulb else cls.stack_ops

    @classmethod
    def missing_operations(cls, supports, *, bulb: bool = False) -> tuple[int, ...]:
        """Operations of :meth:`required_operations` for which ``supports(op)`` is false."""
        return tuple(op for op in cls.required_operations(bulb=bulb) if not supports(op))

    def check_supported(self, *, bulb: bool = False) -> None:
        """Raise :class:`~pipeline.tether.session.UnsupportedCamera` if a flow cannot run.

        The same rules as :func:`pipeline.tether.capabilities.body_capability`
        (both use :meth:`missing_operations` and :attr:`sweep_refusal`).
        """
        self.session.require(self.stack_ops, "capture a focal stack")
        if bulb:
            if self.sweep_refusal:
                model = self.session.device_info.model if self.session.device_info else "camera"
                raise UnsupportedCamera(
                    f"{model} cannot drive the focus in bulb: {self.sweep_refusal}; capture a "
                    "focal stack (tether stack) instead")
            self.session.require(self.bulb_ops, "expose in bulb while driving the focus")

    def start(self) -> None:
        """Remote control and live view on (needed before driving the focus)."""
        raise NotImplementedError

    def drive(self, steps: int) -> None:
        """Move the focus by ``steps`` (signed); updates :attr:`position` and the drive log."""
        if steps:
            self._drive(steps)
            self.drive_log.append((self.clock.now(), steps))

    def drive_commands(self, steps: int) -> int:
        """How many drive commands moving ``steps`` takes (each paced by ``drive_pace_s``)."""
        return 1 if steps else 0

    def _drive(self, steps: int) -> None:
        """Issue the drive; add each acknowledged step to :attr:`position`."""
        raise NotImplementedError

    def settle(self, seconds: float) -> None:
        """Wait after a drive (the lens stops ringing) and take in the camera's events."""
        self.clock.sleep(seconds)

    def capture(self) -> CapturedObject:
        """One exposure at the camera's shutter speed, without autofocus."""
        raise NotImplementedError

    def capture_bulb(self, exposure_s: float) -> CapturedObject:
        """A bulb exposure of ``exposure_s`` seconds without focus motion."""
        self.open_exposure()
        try:
            self.clock.sleep(exposure_s)
        except BaseException:  # Ctrl-C: close the shutter without waiting for the image
            self.abort_exposure()
            raise
        return self.close_exposure()

    def open_exposure(self) -> None:
        """Open the shutter (camera set to bulb)."""
        raise NotImplementedError

    def close_exposure(self) -> CapturedObject:
        """Close the shutter; the captured image."""
        raise NotImplementedError

    def abort_exposure(self) -> None:
        """Close an open shutter without waiting for the image. Never raises."""

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
        """Vendor hook after a download (Canon: TransferComplete; Nikon: delete from SDRAM)."""

    def safe_state(self) -> None:
        """Shutter closed, live view off, remote mode off. Never raises: the camera may be gone."""
        raise NotImplementedError

    def _quietly(self, what: str, func, *args, **kwargs) -> None:
        try:
            func(*args, **kwargs)
        except TetherError as err:
            log.warning("could not %s while restoring the camera: %s", what, err)

    def _poll(self, what: str, step, timeout_s: float | None = None):
        """Call ``step()`` until it returns something, with backoff, up to ``timeout_s``."""
        timeout_s = self.event_timeout_s if timeout_s is None else timeout_s
        deadline = self.clock.now() + timeout_s
        delay = self.session.backoff_s
        while True:
            result = step()
            if result is not None:
                return result
            if self.clock.now() > deadline:
                raise TetherError(f"{what}: nothing after {timeout_s:.0f} s; check the "
                                  "camera's screen for an error (card full, no lens, AF failed)")
            self.session.sleep(delay)
            delay = min(2 * delay, self.session.max_backoff_s)
