"""The emulator's byte tables against bytes real cameras sent, and the host's parsers on them.

The recordings (``/work/shared/data/ptp-recordings``, see SOURCE.txt there) are a
``gphoto2 --debug`` session of a real Canon EOS 60D and a real EOS GetEvent
payload. The byte tables here are written by hand from the documented layouts;
the emulator (:mod:`pipeline.tether.emulated.layouts`) and the host parsers
(``canon``, ``nikon``, ``ptp``) are each checked against them separately.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import pytest

from pipeline.tether import canon, nikon
from pipeline.tether.codes import CanonDPC, CanonEC, CanonOC, NikonEC
from pipeline.tether.emulated import layouts
from pipeline.tether.ptp import DeviceInfo, ObjectInfo

RECORDINGS = Path("/work/shared/data/ptp-recordings")
LOG_60D = RECORDINGS / "canon-eos-60d.debug.log"
VCAM_EVENTS = RECORDINGS / "vcam-eos_events.bin"
needs_recordings = pytest.mark.skipif(not LOG_60D.is_file() or not VCAM_EVENTS.is_file(),
                                      reason="PTP recordings not available")


def hexdumps(path: Path) -> list[bytes]:
    """Every ``Hexdump of N = 0x.. bytes follows:`` block of a gphoto2 --debug log."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    dumps, i = [], 0
    while i < len(lines):
        m = re.search(r"Hexdump of (\d+) = 0x[0-9a-f]+ bytes follows:", lines[i])
        i += 1
        if not m:
            continue
        buf = bytearray()
        while i < len(lines) and re.match(r"^[0-9a-f]{4}  ", lines[i]):
            buf += bytes.fromhex(lines[i][6:55].replace("-", " "))
            i += 1
        dumps.append(bytes(buf[: int(m.group(1))]))
    return dumps


def containers(path: Path, kind: int, code: int) -> list[bytes]:
    """Payloads of the complete containers of one type and code in a log."""
    out = []
    for blob in hexdumps(path):
        if len(blob) >= 12:
            length, ctype, ccode, _tid = struct.unpack_from("<IHHI", blob)
            if (ctype, ccode) == (kind, code) and length == len(blob):
                out.append(blob[12:])
    return out


# --- hand-written byte tables (documented layouts) ---------------------------------------------

# PropValueChanged: size 16, type 0xC189, property, value (a record from the real vcam payload)
PROP_FOCUS_MODE_MF = bytes.fromhex("10000000 89c10000 08d10000 03000000")
# ObjectAddedEx: handle 0x1001 @8, storage 0x20001 @0xC, format 0x3801 @0x10, size 4096 @0x1C,
# parent 0x100000 @0x20, name @0x28, padded to 4 bytes: 0x28 + 13 -> 56
OBJECT_ADDED = bytes.fromhex(
    "38000000 81c10000 01100000 01000200 01380000 00000000 00000000 00100000"
    "00001000 00000000" + "494d475f303030312e4a5047" + "00" + "000000")
# ObjectAddedEx64: as above but 64-bit size @0x1C, parent @0x24, 2nd handle @0x28, name @0x2C
OBJECT_ADDED64 = bytes.fromhex(
    "3c000000 a7c10000 01100000 01000200 01380000 00000000 00000000 00100000"
    "00000000 00001000 01100000" + "494d475f303030312e4a5047" + "00" + "000000")
# RequestObjectTransfer: handle @8, format @0xC, size @0x14, name @0x1C
REQUEST_TRANSFER = bytes.fromhex(
    "2c000000 86c10000 01100000 01380000 00000000 00100000 00000000"
    + "494d475f303030312e4a5047" + "00" + "000000")
# Nikon GetEvent: count 1, ObjectAddedInSDRAM 0xC101 with handle 0xFFFF0001
NIKON_SDRAM_EVENT = bytes.fromhex("0100 01c1 0100ffff")


def test_emulator_event_records_match_the_tables():
    assert layouts.eos_prop_value(0xD108, 3) == PROP_FOCUS_MODE_MF
    assert layouts.eos_object_added(0x1001, 4096, "IMG_0001.JPG", 0x3801) == OBJECT_ADDED
    assert layouts.eos_object_added64(0x1001, 4096, "IMG_0001.JPG", 0x3801) == OBJECT_ADDED64
    assert layouts.eos_request_transfer(0x1001, 4096, "IMG_0001.JPG", 0x3801) == REQUEST_TRANSFER
    assert layouts.nikon_events([(0xC101, 0xFFFF0001)]) == NIKON_SDRAM_EVENT


def test_host_parses_the_tables():
    data = (PROP_FOCUS_MODE_MF + OBJECT_ADDED + OBJECT_ADDED64 + REQUEST_TRANSFER
            + struct.pack("<II", 8, 0))
    events = canon.parse_events(data)
    assert [e.type for e in events] == [CanonEC.PropValueChanged, CanonEC.ObjectAddedEx,
                                        CanonEC.ObjectAddedEx64, CanonEC.RequestObjectTransfer]
    assert events[0].words[:2] == (CanonDPC.FocusMode, 3)
    found = [canon.object_of(e) for e in events[1:]]
    assert [(o.handle, o.size, o.filename, o.transfer, fmt) for o, fmt in found] == [
        (0x1001, 4096, "IMG_0001.JPG", False, 0x3801),
        (0x1001, 4096, "IMG_0001.JPG", False, 0x3801),
        (0x1001, 4096, "IMG_0001.JPG", True, 0x3801),
    ]
    assert nikon.parse_events(NIKON_SDRAM_EVENT) == [(NikonEC.ObjectAddedInSDRAM, 0xFFFF0001)]


def test_object_info_layout_is_the_iso_table():
    # StorageID, format, protection, size, thumb format/size/w/h, image w/h/depth, parent,
    # association type/desc, sequence: 52 bytes, then the file name as a PTP string
    blob = layouts.object_info(storage=0x10001, fmt=0x380D, size=123456, name="DSC_1.TIF",
                               width=320, height=224)
    assert blob[:16] == bytes.fromhex("01000100 0d380000 40e20100 0000 0000")
    assert blob[52] == 10 and blob[53:73].decode("utf-16-le") == "DSC_1.TIF\x00"
    info = ObjectInfo.from_bytes(blob)
    assert (info.size, info.filename, info.object_format, info.image_width) == (
        123456, "DSC_1.TIF", 0x380D, 320)


# --- real bytes ----------------------------------------------------------------------------------


@needs_recordings
def test_real_eos_event_payload_parses_and_matches_the_emulator_records():
    data = VCAM_EVENTS.read_bytes()
    events = canon.parse_events(data)
    assert len(events) == 184
    props = {e.words[0]: e.words[1] for e in events if e.type == CanonEC.PropValueChanged}
    assert props[CanonDPC.FocusMode] == 3 and props[CanonDPC.EVFMode] == 1
    assert props[CanonDPC.CaptureDestination] == 2
    u32_records = [e for e in events if e.type == CanonEC.PropValueChanged and len(e.raw) == 16]
    assert len(u32_records) > 40
    for e in u32_records:  # the emulator builds exactly the bytes the camera sent
        assert layouts.eos_prop_value(e.words[0], e.words[1]) == e.raw


@needs_recordings
def test_real_60d_get_event_data_matches_the_emulator_records():
    payloads = containers(LOG_60D, 2, CanonOC.GetEvent)
    assert len(payloads) >= 15
    checked, other_sizes = 0, set()
    for data in payloads:
        for e in canon.parse_events(data):
            if e.type == CanonEC.PropValueChanged and len(e.raw) == 16:
                assert layouts.eos_prop_value(e.words[0], e.words[1]) == e.raw
                checked += 1
            if e.type == CanonEC.PropValueChanged:  # any length: 13 (one byte) to 200 bytes
                (prop,) = struct.unpack_from("<I", e.raw, 8)
                assert layouts.eos_prop_raw(prop, e.raw[12:]) == e.raw
                other_sizes.add(len(e.raw))
    assert checked >= 20
    assert {13, 23, 76} <= other_sizes  # Owner (1 byte), serial "1280627086", lens name
    assert payloads[-1].endswith(layouts.EOS_TERMINATOR)


@needs_recordings
def test_real_60d_device_info_round_trips_through_both_codecs():
    (raw, *_rest) = containers(LOG_60D, 2, 0x1001)
    info = DeviceInfo.from_bytes(raw)
    assert info.model == "Canon EOS 60D" and info.vendor_extension_id == 6
    assert {CanonOC.DriveLens, CanonOC.RemoteReleaseOn, CanonOC.GetEvent} <= set(info.operations)
    rebuilt = layouts.device_info(
        vendor_extension_id=info.vendor_extension_id, manufacturer=info.manufacturer,
        model=info.model, operations=info.operations, events=info.events,
        properties=info.properties, capture_formats=info.capture_formats,
        image_formats=info.image_formats, serial=info.serial_number,
        standard_version=info.standard_version,
        vendor_extension_version=info.vendor_extension_version,
        vendor_extension_desc=info.vendor_extension_desc, functional_mode=info.functional_mode,
        device_version=info.device_version)
    assert rebuilt == raw


@needs_recordings
def test_host_property_write_is_the_real_60d_data_phase():
    """SetDevicePropValueEx data as gphoto2 sent it to the 60D (CaptureDestination = 4)."""
    sent = containers(LOG_60D, 2, CanonOC.SetDevicePropValueEx)
    assert bytes.fromhex("0c0000001cd1000004000000") in sent
    assert canon.property_data(CanonDPC.CaptureDestination, 4) in sent


def test_emulated_property_dump_values_reach_the_host_whole():
    """The emulator's dump holds values that are not one u32 (as the 60D's): the host keeps
    them whole through a real connect."""
    from pipeline.tether.emulated.device import EmulatedBackend, EmulatedCamera
    from pipeline.tether.emulated.personalities import CANON
    from pipeline.tether.flows import connect

    with connect(EmulatedBackend(EmulatedCamera(CANON))) as camera:
        assert camera.property_bytes[CanonDPC.Owner] == b"\x00"
        assert camera.properties[CanonDPC.Owner] == 0 and camera.property_text(0xD115) == ""
        assert camera.properties[CanonDPC.SerialNumber] == "EMU0001"
        assert camera.properties[CanonDPC.LensName] == "EF50mm f/1.8 (emulated)"
        assert len(camera.property_bytes[CanonDPC.LensName]) == 64
