"""ICC profiles: read the one a frame carries, and carry it into the result.

A frame exported in Adobe RGB or ProPhoto RGB (a raw converter's 16-bit TIFF, a camera's
JPEG set to Adobe RGB) says so in an embedded ICC profile. flexdof decodes integer codes
with the sRGB curve (:mod:`pipeline.io.read`) and encodes the result with it again, so the
result's codes are in the frames' colour space; without the profile a colour-managed viewer
shows them as sRGB (ProPhoto's greens and reds turn dull). The first frame's profile is
carried into every output whose codes are sRGB-encoded (``srgb8``, ``srgb16``): a JPEG's
APP2 chunks (ICC.1 Annex B.4), a PNG's ``iCCP`` chunk, a TIFF's InterColorProfile tag
(34675). Linear outputs (``linear16``, ``float32``) are not in the profile's encoding and
carry none. RAW frames are decoded into sRGB primaries by LibRaw and carry none.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import tifffile

from pipeline.errors import InputError
from pipeline.io.exif import _insert_jpeg_segment, _insert_png_chunk
from pipeline.io.probe import (
    _ICC_HEADER,
    _existing,
    _first_tiff_page,
    _jpeg_structure,
    _kind,
    _png_chunk,
)

_JPEG_CHUNK = 0xFFFF - 2 - len(_ICC_HEADER) - 2  # data bytes per APP2 segment: 65519


def read_icc(path: str | Path) -> bytes | None:
    """The ICC profile a JPEG, PNG or TIFF frame carries, or None (RAW files, none)."""
    p = _existing(path)
    kind = _kind(p)
    if kind == "jpeg":
        return _jpeg_structure(p.read_bytes(), p).icc
    if kind == "png":
        body = _png_chunk(p, b"iCCP") or b""
        name_end = body.find(b"\x00")  # a profile name, its NUL, the compression method
        try:
            return zlib.decompress(body[name_end + 2 :]) if name_end > 0 else None
        except zlib.error:
            return None  # a damaged profile: the pixels are still readable
    if kind == "tiff":
        try:
            with tifffile.TiffFile(p) as tif:
                tag = _first_tiff_page(tif, p).tags.get("InterColorProfile")
                return None if tag is None else bytes(tag.value)
        except (tifffile.TiffFileError, struct.error, ValueError):
            return None
    return None


def insert_jpeg_icc(jpeg: bytes, profile: bytes) -> bytes:
    """``jpeg`` with ``profile`` in APP2 segments after SOI (and a JFIF APP0), in order."""
    parts = [profile[i : i + _JPEG_CHUNK] for i in range(0, len(profile), _JPEG_CHUNK)]
    if not 0 < len(parts) <= 255:
        raise InputError(
            f"the first frame's ICC profile of {len(profile)} bytes does not fit a JPEG's 255 "
            "APP2 chunks: write a .tif or .png"
        )
    for i in reversed(range(len(parts))):  # each goes in after SOI: the last one first
        jpeg = _insert_jpeg_segment(jpeg, 0xE2, _ICC_HEADER + bytes([i + 1, len(parts)]) + parts[i])
    return jpeg


def insert_png_icc(png: bytes, profile: bytes, path: Path) -> bytes:
    """``png`` with an ``iCCP`` chunk (``profile`` deflated) before its first IDAT."""
    return _insert_png_chunk(png, b"iCCP", b"ICC profile\x00\x00" + zlib.compress(profile), path)
