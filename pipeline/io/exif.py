"""EXIF: read a frame's EXIF block, its SubjectDistance (a focus position), and carry
it into JPEG and PNG outputs.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import tifffile

from pipeline.errors import InputError
from pipeline.io.probe import (
    _EXIF_HEADER,
    _existing,
    _first_tiff_page,
    _jpeg_structure,
    _kind,
    _png_chunk,
    _png_chunks,
)


def read_exif(path: str | Path) -> bytes | None:
    """The EXIF block of a JPEG (APP1) or PNG (eXIf chunk), or None.

    Returned as ``b"Exif\\0\\0"`` + the TIFF-structured EXIF data, the form
    :func:`write_image` accepts. TIFF and RAW files keep EXIF in an IFD rather
    than a block; for them this returns None (see :func:`subject_distance_mm`).
    """
    p = _existing(path)
    kind = _kind(p)
    if kind == "jpeg":
        return _jpeg_structure(p.read_bytes(), p).exif
    if kind == "png":
        body = _png_chunk(p, b"eXIf")
        return None if body is None else _EXIF_HEADER + body
    return None


_SUBJECT_DISTANCE = 0x9206  # EXIF SubjectDistance, RATIONAL, metres
_EXIF_IFD = 0x8769
_RATIONAL = 5  # TIFF field type: two unsigned 32-bit integers


def _ifd_entries(tiff: bytes, offset: int, order: str) -> dict[int, tuple[int, int, bytes]]:
    """The entries of the TIFF IFD at ``offset``: tag -> (type, count, 4-byte value field).

    Raises struct.error or IndexError on a truncated block."""
    (count,) = struct.unpack_from(order + "H", tiff, offset)
    entries = {}
    for i in range(count):
        tag, ftype, n = struct.unpack_from(order + "HHI", tiff, offset + 2 + 12 * i)
        start = offset + 2 + 12 * i + 8
        entries[tag] = (ftype, n, tiff[start : start + 4])
    return entries


def _exif_block_subject_distance(block: bytes) -> tuple[int, int] | None:
    """SubjectDistance of an EXIF block (``Exif\\0\\0`` + TIFF structure) as (numerator,
    denominator), or None where it is absent or the block is malformed.

    A direct walk of the TIFF structure (header, IFD0, its Exif IFD pointer, the Exif IFD)
    instead of a general EXIF library: it is the one tag the pipeline reads, and importing
    pillow for it cost about a fiftieth of a whole run on a 7-frame stack.
    """
    tiff = block.removeprefix(_EXIF_HEADER)
    order = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    if order is None:
        return None
    try:
        (ifd0,) = struct.unpack_from(order + "I", tiff, 4)
        pointer = _ifd_entries(tiff, ifd0, order).get(_EXIF_IFD)
        if pointer is None:
            return None
        (exif_ifd,) = struct.unpack_from(order + "I", pointer[2])
        field = _ifd_entries(tiff, exif_ifd, order).get(_SUBJECT_DISTANCE)
        if field is None or field[0] != _RATIONAL or field[1] < 1:
            return None
        (value_at,) = struct.unpack_from(order + "I", field[2])
        return struct.unpack_from(order + "II", tiff, value_at)
    except (struct.error, IndexError):
        return None


def subject_distance_mm(path: str | Path) -> float | None:
    """EXIF SubjectDistance in mm (``math.inf`` for infinity), or None if absent or 0.

    JPEG/PNG via their EXIF block; TIFF and TIFF-based RAW files (DNG, CR2,
    NEF, ARW, ...) via tifffile's EXIF IFD; other RAW containers give None.
    """
    p = _existing(path)
    kind = _kind(p)
    if kind in ("jpeg", "png"):
        block = read_exif(p)
        rational = None if block is None else _exif_block_subject_distance(block)
    else:
        try:
            with tifffile.TiffFile(p) as tif:
                tag = _first_tiff_page(tif, p).tags.get("ExifTag")
                rational = None if tag is None else tag.value.get("SubjectDistance")
        except (tifffile.TiffFileError, struct.error, ValueError):
            return None  # not TIFF-structured (CR3, RAF, ...): no EXIF IFD to read
    if rational is None:
        return None
    numerator, denominator = (float(rational[0]), float(rational[1]))
    if numerator == 0xFFFFFFFF:
        return float("inf")
    if numerator <= 0 or denominator <= 0:
        return None  # 0 means "unknown" in EXIF
    return numerator / denominator * 1000.0


def _insert_jpeg_segment(jpeg: bytes, marker: int, payload: bytes) -> bytes:
    """Insert an APPn segment (``marker`` 0xE0-0xEF) after SOI (and a JFIF APP0 if any)."""
    pos = 2
    if jpeg[2:4] == b"\xff\xe0":
        pos += 2 + struct.unpack(">H", jpeg[4:6])[0]
    segment = bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload
    return jpeg[:pos] + segment + jpeg[pos:]


def _insert_png_chunk(png: bytes, ctype: bytes, body: bytes, path: Path) -> bytes:
    """Insert a chunk of type ``ctype`` before the first IDAT chunk."""
    for kind, start, _end in _png_chunks(png, path):
        if kind == b"IDAT":
            pos = start - 8
            break
    chunk = struct.pack(">I", len(body)) + ctype + body
    chunk += struct.pack(">I", zlib.crc32(ctype + body) & 0xFFFFFFFF)
    return png[:pos] + chunk + png[pos:]


def fits_jpeg(exif: bytes) -> bool:
    """Whether an EXIF block fits a JPEG's one APP1 segment (64 kB; a PNG's eXIf chunk, or a
    TIFF's IFD, may hold more)."""
    return len(exif.removeprefix(_EXIF_HEADER)) + len(_EXIF_HEADER) + 2 <= 0xFFFF


def _insert_jpeg_exif(jpeg: bytes, exif: bytes, path: Path) -> bytes:
    """Insert an APP1 EXIF segment after SOI (and after a JFIF APP0 if there is one)."""
    block = exif if exif.startswith(_EXIF_HEADER) else _EXIF_HEADER + exif
    if not fits_jpeg(block):
        raise InputError(f"{path}: EXIF block of {len(block)} bytes is too large for JPEG APP1")
    return _insert_jpeg_segment(jpeg, 0xE1, block)


def _insert_png_exif(png: bytes, exif: bytes, path: Path) -> bytes:
    """Insert an eXIf chunk before the first IDAT chunk."""
    return _insert_png_chunk(png, b"eXIf", exif.removeprefix(_EXIF_HEADER), path)
