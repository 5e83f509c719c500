"""PTP generic container and dataset codec (pure bytes in, bytes out).

A USB PTP container is ``u32 length, u16 type, u16 code, u32 transaction id``
followed by up to five ``u32`` parameters (command, response, event) or the
payload (data). A container is sent as one USB transfer; a transfer whose
length is an exact multiple of the endpoint's packet size is terminated by a
zero-length packet (ZLP), since only a short packet ends a bulk transfer.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from pipeline.errors import TetherError
from pipeline.tether.codes import ContainerType

HEADER = struct.Struct("<IHHI")
MAX_PARAMS = 5


class ProtocolError(TetherError):
    """Bytes on the wire that are not a valid PTP container or dataset."""


@dataclass(frozen=True)
class Container:
    """One PTP container: ``params`` for command/response/event, ``payload`` for data."""

    type: ContainerType
    code: int
    transaction_id: int
    params: tuple[int, ...] = ()
    payload: bytes = b""

    def __post_init__(self) -> None:
        if len(self.params) > MAX_PARAMS:
            raise ProtocolError(f"a PTP container has at most 5 parameters, got {self.params}")
        if self.params and self.type == ContainerType.DATA:
            raise ProtocolError("a data container carries a payload, not parameters")
        if self.payload and self.type != ContainerType.DATA:
            raise ProtocolError(f"only data containers carry a payload, not {self.type.name}")


def encode_container(container: Container) -> bytes:
    """Bytes of a container (header, then parameters or payload)."""
    body = container.payload + b"".join(struct.pack("<I", p) for p in container.params)
    return (
        HEADER.pack(
            HEADER.size + len(body),
            int(container.type),
            container.code,
            container.transaction_id,
        )
        + body
    )


def container_length(header: bytes) -> int:
    """Total length announced by a container's first bytes (validated)."""
    if len(header) < HEADER.size:
        raise ProtocolError(f"PTP container shorter than its 12-byte header: {len(header)} bytes")
    length, ctype, _code, _tid = HEADER.unpack_from(header)
    if length < HEADER.size or ctype not in ContainerType._value2member_map_:
        raise ProtocolError(
            f"invalid PTP container header: length {length}, type {ctype} (expected 1-4)"
        )
    return length


def decode_container(blob: bytes) -> Container:
    """Parse exactly one container; its announced length must match ``len(blob)``."""
    length = container_length(blob)
    if length != len(blob):
        raise ProtocolError(f"PTP container announces {length} bytes but {len(blob)} arrived")
    _length, ctype, code, tid = HEADER.unpack_from(blob)
    body = bytes(blob[HEADER.size :])
    ctype = ContainerType(ctype)
    if ctype == ContainerType.DATA:
        return Container(ctype, code, tid, payload=body)
    if len(body) % 4 or len(body) > 4 * MAX_PARAMS:
        raise ProtocolError(f"{ctype.name} container has {len(body)} parameter bytes")
    params = struct.unpack(f"<{len(body) // 4}I", body)
    return Container(ctype, code, tid, params=params)


def split_transfers(blob: bytes, packet_size: int, max_transfer: int) -> list[bytes]:
    """The bulk-out writes that send ``blob``: chunks of ``max_transfer``, then a ZLP if due.

    ``max_transfer`` must be a multiple of ``packet_size`` so that only the last
    chunk can be short; ``b""`` is appended when ``len(blob)`` is a multiple of
    the packet size (the zero-length packet that ends the transfer).
    """
    if packet_size <= 0 or max_transfer <= 0 or max_transfer % packet_size:
        raise ValueError(
            f"max_transfer ({max_transfer}) must be a positive multiple of "
            f"packet_size ({packet_size})"
        )
    chunks = [blob[i : i + max_transfer] for i in range(0, len(blob), max_transfer)]
    if len(blob) % packet_size == 0:
        chunks.append(b"")
    return chunks


def read_sizes(length: int, packet_size: int, max_transfer: int) -> list[int]:
    """Read requests (multiples of the packet size) that fetch the rest of a container."""
    sizes = []
    remaining = length
    while remaining > 0:
        want = min(max_transfer, -(-remaining // packet_size) * packet_size)
        sizes.append(want)
        remaining -= want
    return sizes


# --- datasets (PTP strings, arrays, DeviceInfo, ObjectInfo) ---------------------------------


class Reader:
    """Sequential little-endian reader over a dataset."""

    def __init__(self, data: bytes, what: str) -> None:
        self.data, self.pos, self.what = bytes(data), 0, what

    def take(self, fmt: str) -> int:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise ProtocolError(f"{self.what} dataset truncated at byte {self.pos}")
        (value,) = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return value

    def array(self, fmt: str) -> tuple[int, ...]:
        return tuple(self.take(fmt) for _ in range(self.take("I")))

    def string(self) -> str:
        count = self.take("B")  # number of UCS-2 characters including the terminating NUL
        if count == 0:
            return ""
        raw = self.data[self.pos : self.pos + 2 * count]
        if len(raw) != 2 * count:
            raise ProtocolError(f"{self.what} dataset truncated inside a string")
        self.pos += 2 * count
        return raw.decode("utf-16-le").rstrip("\x00")


def pack_string(text: str) -> bytes:
    """PTP string: u8 character count (with NUL), UCS-2LE characters, NUL."""
    if not text:
        return b"\x00"
    encoded = (text + "\x00").encode("utf-16-le")
    if len(encoded) // 2 > 255:
        raise ValueError(f"PTP strings hold at most 254 characters, got {len(text)}")
    return bytes([len(encoded) // 2]) + encoded


def pack_array(fmt: str, values: Sequence[int]) -> bytes:
    return struct.pack(f"<I{len(values)}{fmt}", len(values), *values)


@dataclass(frozen=True)
class DeviceInfo:
    """The GetDeviceInfo dataset (ISO 15740 5.5.1)."""

    vendor_extension_id: int
    manufacturer: str
    model: str
    operations: tuple[int, ...]
    events: tuple[int, ...] = ()
    properties: tuple[int, ...] = ()
    standard_version: int = 100
    vendor_extension_version: int = 100
    vendor_extension_desc: str = ""
    functional_mode: int = 0
    capture_formats: tuple[int, ...] = ()
    image_formats: tuple[int, ...] = ()
    device_version: str = "1.0"
    serial_number: str = ""

    def to_bytes(self) -> bytes:
        return b"".join(
            (
                struct.pack("<HIH", self.standard_version, self.vendor_extension_id,
                            self.vendor_extension_version),
                pack_string(self.vendor_extension_desc),
                struct.pack("<H", self.functional_mode),
                pack_array("H", self.operations),
                pack_array("H", self.events),
                pack_array("H", self.properties),
                pack_array("H", self.capture_formats),
                pack_array("H", self.image_formats),
                pack_string(self.manufacturer),
                pack_string(self.model),
                pack_string(self.device_version),
                pack_string(self.serial_number),
            )
        )

    @classmethod
    def from_bytes(cls, data: bytes) -> DeviceInfo:
        r = Reader(data, "DeviceInfo")
        std, ext_id, ext_ver = r.take("H"), r.take("I"), r.take("H")
        desc, mode = r.string(), r.take("H")
        ops, events, props, capture, image = (r.array("H") for _ in range(5))
        manufacturer, model, version, serial = (r.string() for _ in range(4))
        return cls(
            vendor_extension_id=ext_id, manufacturer=manufacturer, model=model,
            operations=ops, events=events, properties=props, standard_version=std,
            vendor_extension_version=ext_ver, vendor_extension_desc=desc, functional_mode=mode,
            capture_formats=capture, image_formats=image, device_version=version,
            serial_number=serial,
        )


_OBJECT_INFO_HEAD = struct.Struct("<IHHIHIIIIIIIHII")


@dataclass(frozen=True)
class ObjectInfo:
    """The fields of the ObjectInfo dataset (ISO 15740 5.5.2) a download needs."""

    size: int
    filename: str
    object_format: int = 0x3801  # EXIF/JPEG
    storage_id: int = 0
    image_width: int = 0
    image_height: int = 0

    def to_bytes(self) -> bytes:
        head = _OBJECT_INFO_HEAD.pack(
            self.storage_id, self.object_format, 0, self.size, 0, 0, 0, 0,
            self.image_width, self.image_height, 0, 0, 0, 0, 0,
        )
        return head + pack_string(self.filename) + b"".join(pack_string("") for _ in range(3))

    @classmethod
    def from_bytes(cls, data: bytes) -> ObjectInfo:
        if len(data) < _OBJECT_INFO_HEAD.size + 1:
            raise ProtocolError(f"ObjectInfo dataset too short: {len(data)} bytes")
        fields = _OBJECT_INFO_HEAD.unpack_from(data)
        r = Reader(data, "ObjectInfo")
        r.pos = _OBJECT_INFO_HEAD.size
        return cls(
            size=fields[3], filename=r.string(), object_format=fields[1],
            storage_id=fields[0], image_width=fields[8], image_height=fields[9],
        )


def iter_chunks(total: int, chunk: int) -> Iterable[tuple[int, int]]:
    """(offset, length) pairs covering ``total`` bytes in pieces of at most ``chunk``."""
    for offset in range(0, total, chunk):
        yield offset, min(chunk, total - offset)
