"""Byte layouts the emulated camera sends, written from the documented formats.

Nothing here uses the host's encoders (:mod:`pipeline.tether.ptp`,
``canon``/``nikon``): the emulator must be able to disagree with the host. The
offsets follow ISO 15740 (containers, DeviceInfo, ObjectInfo) and the Canon EOS
/ Nikon vendor layouts as libgphoto2 documents them (``ptp-pack.c``); the tests
check these tables against bytes recorded from real cameras
(``/work/shared/data/ptp-recordings``).

Canon EOS GetEvent records are ``u32 size, u32 type`` and a type-specific body:

=====================  ====================================================================
PropValueChanged       0x08 property u32, 0x0C value: as long as the record (1, 2 or 4
                       bytes for numbers; strings and arrays up to 100+ bytes)
CameraStatusChanged    0x08 status u32
ObjectAddedEx 0xC181   0x08 handle, 0x0C storage, 0x10 format u16, 0x1C size u32,
                       0x20 parent, 0x28 file name (ASCII, NUL)
ObjectAddedEx64 0xC1A7 0x08 handle, 0x0C storage, 0x10 format u16, 0x1C size u64,
                       0x24 parent, 0x28 second handle, 0x2C file name
RequestObjectTransfer  0x08 handle, 0x0C format u16, 0x14 size u32, 0x1C file name
terminator             size 8, type 0
=====================  ====================================================================

Nikon GetEvent data is ``u16 count`` then ``count`` x ``(u16 code, u32 parameter)``.
"""

from __future__ import annotations

import struct


def container(kind: int, code: int, tid: int, body: bytes) -> bytes:
    """A USB PTP container: u32 length, u16 type, u16 code, u32 transaction id, body."""
    return struct.pack("<IHHI", 12 + len(body), kind, code, tid) + body


def params(*values: int) -> bytes:
    return b"".join(struct.pack("<I", v) for v in values)


def _record(kind: int, size: int, fields: list[tuple[int, str, object]]) -> bytes:
    """A record of ``size`` bytes: u32 size @0, u32 type @4, then (offset, format, value)."""
    buf = bytearray(size)
    struct.pack_into("<II", buf, 0, size, kind)
    for offset, fmt, value in fields:
        if fmt == "z":
            raw = value.encode("ascii") + b"\x00"
            buf[offset : offset + len(raw)] = raw
        else:
            struct.pack_into("<" + fmt, buf, offset, value)
    return bytes(buf)


def eos_prop_value(prop: int, value: int) -> bytes:
    """PropValueChanged (0xC189) of a u32 property: 16 bytes."""
    return _record(0xC189, 16, [(0x08, "I", prop), (0x0C, "I", value)])


def eos_prop_raw(prop: int, value: bytes) -> bytes:
    """PropValueChanged (0xC189) of any value: 12 + ``len(value)`` bytes (the 60D sends 13-byte
    records for one-byte values, 22-23 for its serial number string, 76 for the lens name)."""
    return struct.pack("<III", 12 + len(value), 0xC189, prop) + bytes(value)


def eos_camera_status(status: int) -> bytes:
    """CameraStatusChanged (0xC18B): 12 bytes."""
    return _record(0xC18B, 12, [(0x08, "I", status)])


def eos_object_added(handle: int, size: int, name: str, fmt: int, *, storage: int = 0x00020001,
                     parent: int = 0x00100000) -> bytes:
    """ObjectAddedEx (0xC181); the name at 0x28."""
    length = 0x28 + len(name) + 1
    length += -length % 4
    return _record(0xC181, length, [(0x08, "I", handle), (0x0C, "I", storage), (0x10, "H", fmt),
                                    (0x1C, "I", size), (0x20, "I", parent), (0x28, "z", name)])


def eos_object_added64(handle: int, size: int, name: str, fmt: int, *,
                       storage: int = 0x00020001, parent: int = 0x00100000) -> bytes:
    """ObjectAddedEx64 (0xC1A7, EOS R era); 64-bit size at 0x1C, the name at 0x2C."""
    length = 0x2C + len(name) + 1
    length += -length % 4
    return _record(0xC1A7, length, [(0x08, "I", handle), (0x0C, "I", storage), (0x10, "H", fmt),
                                    (0x1C, "Q", size), (0x24, "I", parent), (0x28, "I", handle),
                                    (0x2C, "z", name)])


def eos_request_transfer(handle: int, size: int, name: str, fmt: int) -> bytes:
    """RequestObjectTransfer (0xC186): an image held in RAM for the host; name at 0x1C."""
    length = 0x1C + len(name) + 1
    length += -length % 4
    return _record(0xC186, length, [(0x08, "I", handle), (0x0C, "H", fmt), (0x14, "I", size),
                                    (0x1C, "z", name)])


EOS_TERMINATOR = struct.pack("<II", 8, 0)


def nikon_events(events: list[tuple[int, int]]) -> bytes:
    """Nikon GetEvent (0x90C7) data."""
    out = bytearray(struct.pack("<H", len(events)))
    for code, param in events:
        out += struct.pack("<HI", code, param)
    return bytes(out)


def ptp_string(text: str) -> bytes:
    """u8 count of UCS-2 characters including the NUL, the characters, the NUL; empty: 0."""
    if not text:
        return b"\x00"
    units = (text + "\x00").encode("utf-16-le")
    return bytes([len(units) // 2]) + units


def u16_array(values) -> bytes:
    return struct.pack(f"<I{len(values)}H", len(values), *values)


def device_info(*, vendor_extension_id: int, manufacturer: str, model: str, operations,
                events=(), properties=(), capture_formats=(), image_formats=(0x3801,),
                serial: str = "EMU0001", standard_version: int = 100,
                vendor_extension_version: int = 100, vendor_extension_desc: str = "",
                functional_mode: int = 0, device_version: str = "1.0") -> bytes:
    """GetDeviceInfo dataset (ISO 15740 5.5.1): u16 standard version, u32 vendor extension
    id, u16 its version, string description, u16 functional mode, five u16 arrays
    (operations, events, properties, capture formats, image formats), four strings
    (manufacturer, model, device version, serial number)."""
    return b"".join((
        struct.pack("<HIH", standard_version, vendor_extension_id, vendor_extension_version),
        ptp_string(vendor_extension_desc), struct.pack("<H", functional_mode),
        u16_array(operations), u16_array(events), u16_array(properties),
        u16_array(capture_formats), u16_array(image_formats), ptp_string(manufacturer),
        ptp_string(model), ptp_string(device_version), ptp_string(serial),
    ))


def object_info(*, storage: int, fmt: int, size: int, name: str, width: int = 0,
                height: int = 0) -> bytes:
    """ObjectInfo dataset (ISO 15740 5.5.2): 52 fixed bytes, then four strings."""
    head = struct.pack("<IHHIHIIIIIIIHII", storage, fmt, 0, size, 0, 0, 0, 0, width, height,
                       0, 0, 0, 0, 0)
    return head + ptp_string(name) + ptp_string("") * 3


def device_prop_value_u8(value: int) -> bytes:
    """GetDevicePropValue data of a UINT8 property."""
    return struct.pack("<B", value)
