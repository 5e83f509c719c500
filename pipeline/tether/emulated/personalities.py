"""Camera models the emulator can play (``--emulate canon|nikon --personality NAME``).

A personality fixes what differs between bodies: USB ids, what GetDeviceInfo
lists (and what the body does but hides), how new images are announced, the
remote-mode value, whether a capture drops live view, whether the focus drive
works while the shutter is open, how long the motor and the body stay busy.
Values are models of real behaviour as libgphoto2 and other tools describe it,
not measurements.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from pipeline.errors import InputError
from pipeline.tether.codes import OC, CanonOC, NikonOC

_COMMON_OPS = (OC.GetDeviceInfo, OC.OpenSession, OC.CloseSession, OC.GetObjectInfo,
               OC.GetObject, OC.DeleteObject, OC.GetDevicePropValue, OC.GetPartialObject)


@dataclass(frozen=True)
class Personality:
    """A camera model.

    Attributes
    ----------
    name, vendor : str
        Personality name; ``"canon"`` or ``"nikon"``.
    operations : tuple of int
        Operations the body performs; ``hidden_ops`` of them are left out of GetDeviceInfo.
    object_event : str
        Canon: ``"ex"`` (ObjectAddedEx 0xC181) or ``"ex64"`` (ObjectAddedEx64 0xC1A7).
    remote_mode : int
        Canon SetRemoteMode value that enables remote control (1; EOS M 0x15).
    drops_live_view : bool
        A capture ends live view (Nikon DSLRs).
    drive_while_exposing : bool
        The focus drive works with the shutter open (what a sweep needs).
    drive_s : dict
        Motor time of one Canon DriveLens per step size, s; Nikon: s per step.
    drive_overlap : str
        A drive arriving while the motor runs is ``"busy"`` (0x2019) or ``"drop"``
        (answered OK, ignored).
    ready_busy_s : float
        Nikon DeviceReady stays busy this long after a capture (processing, NR).
    image_delay_s : float
        Canon: the new-image event comes this long after the shot (long-exposure NR).
    omit_zlp : bool
        The body does not send the zero-length packet after a container that ends
        on a packet boundary.
    """

    name: str
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
    hidden_ops: frozenset = frozenset()
    object_event: str = "ex"
    remote_mode: int = 1
    evf_mode: int = 0  # EVFMode (0xD1B1) at power-on
    capture_destination: int = 2  # Canon CaptureDestination: 2 card, 4 PC
    focus_mode: int = 0  # Canon FocusMode: 0 one shot (lens switch AF), 3 lens switch MF
    drops_live_view: bool = False
    drive_while_exposing: bool = False
    drive_s: dict = field(default_factory=lambda: {1: 0.05, 2: 0.15, 3: 0.35})
    drive_overlap: str = "drop"
    ready_busy_s: float = 1.5
    image_delay_s: float = 0.0  # Canon: the image is announced this long after the shot
    chatter_s: float = 0.0  # Canon: a property event (TempStatus) this often, unasked
    omit_zlp: bool = False

    @property
    def listed_operations(self) -> tuple[int, ...]:
        """What GetDeviceInfo reports."""
        return tuple(op for op in self.operations if op not in self.hidden_ops)

    def but(self, **changes) -> Personality:
        """A copy with some attributes changed."""
        return replace(self, **changes)


_CANON_OPS = (*_COMMON_OPS, *CanonOC)
_NIKON_OPS = (*_COMMON_OPS, *NikonOC)

# the recorded EOS 60D reports vendor extension 6 (Microsoft/MTP), not Canon's 0xB:
# the driver must then come from the USB vendor id
CANON = Personality(
    "eos-dslr", "canon", 0x04A9, 0x3215, "Canon Inc.", "Canon EOS 60D (emulated)", 0x00000006,
    _CANON_OPS, "jpeg", {1: 1, 2: 4, 3: 16},
)
EOS_R = CANON.but(name="eos-r", id_product=0x32D2, model="Canon EOS R (emulated)",
                  vendor_extension_id=0x0000000B, object_event="ex64")
EOS_M = CANON.but(name="eos-m", id_product=0x3271, model="Canon EOS M50 (emulated)",
                  remote_mode=0x15)
EOS_SWEEP = CANON.but(name="eos-sweep", model="Canon EOS (emulated, drives while exposing)",
                      drive_while_exposing=True)
NIKON = Personality(
    "nikon-dslr", "nikon", 0x04B0, 0x0429, "Nikon Corporation", "Nikon D5100 (emulated)",
    0x0000000A, _NIKON_OPS, "tiff", drops_live_view=True, drive_s={1: 0.001},
    drive_overlap="busy",
)

PERSONALITIES = {p.name: p for p in (CANON, EOS_R, EOS_M, EOS_SWEEP, NIKON)}
DEFAULT = {"canon": CANON, "nikon": NIKON}


def personality(vendor: str, name: str | None = None) -> Personality:
    """The named personality (default: the vendor's DSLR); it must be of ``vendor``."""
    if name is None:
        return DEFAULT[vendor]
    found = PERSONALITIES.get(name)
    if found is None or found.vendor != vendor:
        names = ", ".join(n for n, p in PERSONALITIES.items() if p.vendor == vendor)
        raise InputError(f"--personality {name!r} is not an emulated {vendor} body; "
                         f"choose one of {names}")
    return found
