"""Which bodies the tether code can drive, decided from GetDeviceInfo alone.

:func:`body_capability` takes the :class:`~pipeline.tether.ptp.DeviceInfo` that
:meth:`PtpSession.open() <pipeline.tether.session.PtpSession.open>` gets from the
camera and says whether the focal-stack flow and the focus-sweep flow can run
on it, and if not, why. It asks the vendor driver itself
(:meth:`FocusCamera.missing_operations
<pipeline.tether.base.FocusCamera.missing_operations>` and
:attr:`~pipeline.tether.base.FocusCamera.sweep_refusal`, the rules
:meth:`~pipeline.tether.base.FocusCamera.check_supported` enforces), so the
decision and the code path cannot drift apart; the reasons name what a body
lacks in the terms of the flow (no lens drive, no live view, only the one-shot
release, no bulb path on Nikon, ...). :func:`pipeline.tether.flows.connect`
runs it on the camera's own GetDeviceInfo right after the session opens.

:func:`device_info_from_listing` is a data adapter for tests and the body
table: it builds the same ``DeviceInfo`` from a ``gphoto2 --summary`` /
``--debug`` listing of a body (the "Device info" block with its operation,
event and property lists).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path

from pipeline.errors import InputError
from pipeline.tether.codes import (
    PTP_VENDOR_EXTENSION_IDS,
    CanonOC,
    NikonOC,
    operation_name,
)
from pipeline.tether.dispatch import DRIVERS
from pipeline.tether.ptp import DeviceInfo

__all__ = [
    "BodyCapability",
    "CanonLiveViewOC",
    "body_capability",
    "device_info_from_listing",
    "vendor_of",
]


class CanonLiveViewOC(IntEnum):
    """Canon EOS live-view operations (``PTP_OC_CANON_EOS_*`` in libgphoto2's ``ptp.h``).

    Not used by the driver (it switches live view on through the
    EVFOutputDevice property), only as evidence that a body has live view
    over USB when explaining a refusal.
    """

    InitiateViewfinder = 0x9151
    TerminateViewfinder = 0x9152
    GetViewFinderData = 0x9153


_MAKERS = {"canon": "canon", "nikon": "nikon"}  # manufacturer substring -> vendor
_CANON_REMOTE = (CanonOC.SetRemoteMode, CanonOC.SetEventMode, CanonOC.GetEvent)
_CANON_RELEASE = (CanonOC.RemoteReleaseOn, CanonOC.RemoteReleaseOff)
_NIKON_LIVE = (NikonOC.StartLiveView, NikonOC.MfDrive)


def vendor_of(info: DeviceInfo) -> str | None:
    """``"canon"``, ``"nikon"`` or None, from the vendor extension id or the manufacturer.

    Real EOS bodies report the Microsoft extension id 0x6 (libgphoto2 then
    rewrites it to Canon's 0xB), and some Nikon bodies 0x6 or 0xFFFFFFFF in MTP
    mode; the manufacturer string decides then, as the USB vendor id does in
    :meth:`PtpSession.open <pipeline.tether.session.PtpSession.open>`.
    """
    vendor = PTP_VENDOR_EXTENSION_IDS.get(info.vendor_extension_id)
    if vendor:
        return vendor
    maker = info.manufacturer.lower()
    return next((v for key, v in _MAKERS.items() if key in maker), None)


@dataclass(frozen=True)
class BodyCapability:
    """What the tether flows can do with one body.

    Attributes
    ----------
    model, vendor : str, str or None
    stack, sweep : bool
        Whether the focal-stack flow / the focus-sweep flow (bulb exposure
        while driving the focus) can run.
    stack_missing, sweep_missing : tuple of int
        Operations the flow needs that GetDeviceInfo does not list (empty for a
        sweep the driver refuses whatever the body lists, e.g. on Nikon).
    stack_reason, sweep_reason : str
        Empty when accepted; else one line saying why (category, then details).
    """

    model: str
    vendor: str | None
    stack: bool
    sweep: bool
    stack_missing: tuple[int, ...]
    sweep_missing: tuple[int, ...]
    stack_reason: str
    sweep_reason: str

    @property
    def category(self) -> str:
        """The short reason of the first refusal (for tables); ``"accepted"`` if none."""
        reason = self.stack_reason or self.sweep_reason
        return reason.split(" (", 1)[0] if reason else "accepted"

    def refusal(self, *, sweep: bool = False) -> str:
        """One line for a refused flow, naming the body and why; ``""`` if accepted."""
        if sweep and not self.sweep:
            instead = "; capture a focal stack (tether stack) instead" if self.stack else ""
            return f"{self.model} cannot run a focus sweep: {self.sweep_reason}{instead}"
        if not self.stack:
            return f"{self.model} cannot capture a focal stack: {self.stack_reason}"
        return ""


def _names(codes, vendor: str | None) -> str:
    return ", ".join(operation_name(c, vendor) for c in codes)


def _why(vendor: str, ops: frozenset[int], missing: tuple[int, ...]) -> str:
    """One-line reason for a refusal: a category, then the missing operations."""
    lacks = f"(lacks {_names(missing, vendor)})"
    if vendor == "canon":
        if all(op in missing for op in _CANON_REMOTE):
            return f"no EOS remote-control operations (older Canon PTP protocol) {lacks}"
        if CanonOC.DriveLens in missing:
            if any(op in ops for op in CanonLiveViewOC):
                return f"live view but no DriveLens in GetDeviceInfo {lacks}"
            return f"no live view or DriveLens in GetDeviceInfo {lacks}"
        if any(op in missing for op in _CANON_RELEASE):
            if CanonOC.RemoteRelease in ops:
                return f"only the one-shot RemoteRelease, no RemoteReleaseOn/Off {lacks}"
            return f"no RemoteReleaseOn/Off {lacks}"
    if vendor == "nikon":
        if not any(0x9000 <= op < 0x9800 for op in ops):
            return ("lists no Nikon vendor operations (live view, MfDrive and SDRAM capture "
                    f"hidden) {lacks}")
        if any(op in missing for op in _NIKON_LIVE):
            return f"no live view / MfDrive in GetDeviceInfo {lacks}"
        if NikonOC.InitiateCaptureRecInSdram in missing:
            return f"no capture into SDRAM {lacks}"
    return f"missing operations {lacks}"


def body_capability(info: DeviceInfo, extra_operations=()) -> BodyCapability:
    """Decide from GetDeviceInfo whether the stack and sweep flows can run on a body.

    Parameters
    ----------
    info : DeviceInfo
        As returned by ``PtpSession.open()`` (or built by :func:`device_info_from_listing`).
    extra_operations : iterable of int
        Operations the body performs although GetDeviceInfo hides them
        (``PtpSession.extra_operations``, from ``connect(known_operations=...)``).

    Returns
    -------
    BodyCapability
        ``stack`` needs every operation of the vendor driver's stack flow,
        ``sweep`` those of its sweep flow (:meth:`FocusCamera.missing_operations
        <pipeline.tether.base.FocusCamera.missing_operations>`), and a driver
        without a sweep path (:attr:`~pipeline.tether.base.FocusCamera.sweep_refusal`:
        Nikon) refuses every sweep. A body of another vendor is refused for both.

    Notes
    -----
    Only what GetDeviceInfo lists is judged: a body may still refuse an
    operation at run time (e.g. Canon bodies refuse DriveLens while the
    shutter is open, and the sweep flow then falls back to a dense stack).
    """
    vendor = vendor_of(info)
    model = info.model or info.manufacturer or "camera"
    driver = DRIVERS.get(vendor)
    if driver is None:
        reason = (f"not a Canon EOS or Nikon body (vendor extension "
                  f"0x{info.vendor_extension_id:x}, manufacturer {info.manufacturer!r})")
        return BodyCapability(model, vendor, False, False, (), (), reason, reason)
    ops = frozenset(info.operations) | frozenset(extra_operations)
    stack_missing = driver.missing_operations(ops.__contains__)
    stack_reason = _why(vendor, ops, stack_missing) if stack_missing else ""
    if stack_missing:  # the sweep flow needs the stack's operations first
        sweep_missing, sweep_reason = stack_missing, stack_reason
    elif driver.sweep_refusal:
        sweep_missing, sweep_reason = (), driver.sweep_refusal
    else:
        sweep_missing = driver.missing_operations(ops.__contains__, bulb=True)
        sweep_reason = _why(vendor, ops, sweep_missing) if sweep_missing else ""
    return BodyCapability(model, vendor, not stack_missing, not sweep_reason, stack_missing,
                          sweep_missing, stack_reason, sweep_reason)


# --- data adapter: gphoto2 listings -> DeviceInfo -------------------------------------------

_LOG_PREFIX = re.compile(r"^\s*(?:\d+\.\d+\s+)?[\w/.\-]+\s*\(\d\):\s?")
_CODE = re.compile(r"^\s*0x([0-9a-fA-F]{4})\b")
_FIELD = re.compile(r"^\s*(manufacturer|model|vendor extension id|serial number|device version)"
                    r"\s*:\s*(.*?)\s*$", re.IGNORECASE)
_SECTIONS = {"supported operations:": "operations", "events supported:": "events",
             "device properties supported:": "properties"}
_LOOKBACK = 25  # lines before "Supported operations:" searched for the header fields


def _codes(lines: list[str], start: int) -> tuple[tuple[int, ...], int]:
    """Hex codes listed from ``start`` on (blank lines allowed); (codes, next line)."""
    codes, i = [], start
    while i < len(lines):
        match = _CODE.match(lines[i])
        if match:
            codes.append(int(match.group(1), 16))
        elif lines[i].strip():
            break
        i += 1
    return tuple(codes), i


_KIND_BY_NIBBLE = {0x1: "operations", 0x9: "operations", 0x4: "events", 0xC: "events",
                   0x5: "properties", 0xD: "properties"}  # PTP code ranges (ISO 15740)
_FIELD_LINE = re.compile(r"^\s*[A-Za-z][\w ]*:")
_FORWARD = 12  # lines after "Vendor extension ID" searched for the start of the lists


def _headerless_codes(lines: list[str], start: int) -> tuple[dict[str, tuple[int, ...]], int]:
    """Code lists without section headers (blank-line separated): sorted by PTP code range."""
    lists: dict[str, list[int]] = {"operations": [], "events": [], "properties": []}
    i = start
    while i < len(lines):
        match = _CODE.match(lines[i])
        if match:
            code = int(match.group(1), 16)
            kind = _KIND_BY_NIBBLE.get(code >> 12)
            if kind:
                lists[kind].append(code)
        elif lines[i].strip():
            break
        i += 1
    return {k: tuple(v) for k, v in lists.items()}, i


def _blocks(text: str, where: str) -> list[DeviceInfo]:
    """Every "Device info" block (vendor extension id followed by code lists) of a listing."""
    lines = [_LOG_PREFIX.sub("", line, count=1) for line in text.splitlines()]
    blocks = []
    for index, line in enumerate(lines):
        match = _FIELD.match(line)
        if not match or match.group(1).lower() != "vendor extension id":
            continue
        ext = re.match(r"0x([0-9a-fA-F]+)", match.group(2))
        if not ext:
            raise InputError(f"{where}:{index + 1}: 'Vendor extension ID' is not a hex number: "
                             f"{match.group(2)!r}")
        fields: dict[str, str] = {}
        for previous in lines[max(0, index - _LOOKBACK):index]:
            found = _FIELD.match(previous)
            if found:
                fields[found.group(1).lower()] = found.group(2)
        i = index + 1
        while i < min(len(lines), index + _FORWARD) and not (
            _CODE.match(lines[i]) or lines[i].strip().lower() in _SECTIONS
        ):
            if lines[i].strip() and not _FIELD_LINE.match(lines[i]):
                break
            i += 1
        if i >= len(lines):
            continue
        lists: dict[str, tuple[int, ...]] = {}
        if _CODE.match(lines[i]):  # lists without their headers (seen in some listings)
            lists, i = _headerless_codes(lines, i)
        while i < len(lines) and lines[i].strip().lower() in _SECTIONS:
            name = _SECTIONS[lines[i].strip().lower()]
            lists[name], i = _codes(lines, i + 1)
        if not lists.get("operations"):
            continue  # a summary without the device info lists
        blocks.append(DeviceInfo(
            vendor_extension_id=int(ext.group(1), 16),
            manufacturer=fields.get("manufacturer", ""),
            model=fields.get("model", ""),
            operations=lists.get("operations", ()),
            events=lists.get("events", ()),
            properties=lists.get("properties", ()),
            device_version=fields.get("device version", ""),
            serial_number=fields.get("serial number", "").strip("'"),
        ))
    return blocks


def device_info_from_listing(path: str | Path) -> DeviceInfo | None:
    """The GetDeviceInfo contents of a body's ``gphoto2 --summary`` / ``--debug`` listing.

    Parameters
    ----------
    path : str or Path
        A text file holding at least one "Device info" block: ``Manufacturer:``,
        ``Model:``, ``Vendor extension ID: 0x..`` and the ``Supported
        operations:`` / ``Events Supported:`` / ``Device Properties Supported:``
        lists of ``0xNNNN`` codes (debug-log prefixes such as
        ``print_debug_deviceinfo (2):`` are ignored).

    Returns
    -------
    DeviceInfo or None
        Of the block listing the most operations (a listing may hold several,
        e.g. one per USB mode); None if the file has no operation list at all
        (a summary without the device info block, or a config dump).
        Lists printed without their section headers are sorted into
        operations, events and properties by PTP code range.

    Raises
    ------
    InputError
        The file cannot be read, or a vendor extension id is not a hex number.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except OSError as err:
        raise InputError(f"{path}: cannot read the listing: {err.strerror or err}") from err
    blocks = _blocks(text, str(path))
    if not blocks:
        return None
    return max(blocks, key=lambda b: (len(b.operations),
                                      b.vendor_extension_id in PTP_VENDOR_EXTENSION_IDS))
