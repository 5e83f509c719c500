"""What an image file is before decoding it: its kind by extension, its size and
channels from the header, and truncation (JPEG/PNG structure, RAW, TIFF).
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import rawpy
import tifffile

from pipeline.errors import InputError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers carry the image size (C4 DHT, C8 JPG, CC DAC are not SOFs).
_EXIF_HEADER = b"Exif\x00\x00"  # APP1 segments that carry EXIF start with it
_ICC_HEADER = b"ICC_PROFILE\x00"  # APP2 segments that carry an ICC profile (ICC.1 Annex B)
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


# --- reading ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FrameInfo:
    """What :func:`read_frame` will return, read from the header only."""

    rows: int
    cols: int
    channels: int  # 1 (grey) or 3 (RGB)

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.rows, self.cols) if self.channels == 1 else (self.rows, self.cols, 3)

    def describe(self) -> str:
        return f"{self.cols}x{self.rows} px, {self.channels} channel(s)"


@dataclasses.dataclass(frozen=True)
class _JpegLayout:
    rows: int
    cols: int
    components: int
    exif: bytes | None
    icc: bytes | None = None  # the ICC profile, its APP2 chunks joined in their order


def _jpeg_structure(data: bytes, path: Path) -> _JpegLayout:
    """Walk the JPEG markers: size, components and EXIF; refuse truncated files.

    Entropy-coded data escapes 0xFF as 0xFF00, so after the first SOS the only
    0xFFD9 is the EOI marker; a file without it was cut short.
    """
    if not data.startswith(b"\xff\xd8"):
        raise InputError(f"{path}: not a JPEG file (no SOI marker 0xFFD8 at the start)")
    pos, size, exif, icc = 2, None, None, {}
    while True:
        while data[pos + 1 : pos + 2] == b"\xff":
            pos += 1  # fill bytes before a marker
        if pos + 4 > len(data) or data[pos] != 0xFF:
            raise InputError(
                f"{path}: truncated or corrupt JPEG (bad marker structure at byte {pos} of "
                f"{len(data)}); re-copy or re-export the file"
            )
        marker = data[pos + 1]
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        segment = data[pos + 4 : pos + 2 + length]
        if len(segment) != length - 2:
            raise InputError(f"{path}: truncated JPEG (segment 0xFF{marker:02X} cut short)")
        if marker in _JPEG_SOF and size is None:
            _precision, rows, cols, components = struct.unpack(">BHHB", segment[:6])
            size = (rows, cols, components)
        elif marker == 0xE1 and exif is None and segment.startswith(_EXIF_HEADER):
            exif = bytes(segment)
        elif marker == 0xE2 and segment.startswith(_ICC_HEADER) and len(segment) > 14:
            icc[segment[12]] = bytes(segment[14:])  # sequence number, count, then the data
        elif marker == 0xDA:  # start of scan: the entropy-coded data follows
            if size is None:
                raise InputError(f"{path}: corrupt JPEG (no SOF marker before the scan)")
            if data.find(b"\xff\xd9", pos + 2 + length) < 0:
                raise InputError(
                    f"{path}: truncated JPEG (no EOI marker 0xFFD9 after the image data: "
                    "the file was cut short); re-copy or re-export the file"
                )
            profile = b"".join(icc[k] for k in sorted(icc)) if icc else None
            return _JpegLayout(size[0], size[1], size[2], exif, profile)
        pos += 2 + length


_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 3, 6: 3}  # colour type -> channels after decoding


def _png_chunks(data: bytes, path: Path) -> list[tuple[bytes, int, int]]:
    """(type, start, end) of every chunk's data up to IEND; refuse truncated files."""
    if not data.startswith(_PNG_SIGNATURE):
        raise InputError(f"{path}: not a PNG file (bad signature)")
    chunks, pos = [], len(_PNG_SIGNATURE)
    while True:
        if pos + 8 > len(data):
            raise InputError(
                f"{path}: truncated PNG (no IEND chunk: the file was cut short); "
                "re-copy or re-export the file"
            )
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 8 + length
        if end + 4 > len(data):
            raise InputError(f"{path}: truncated PNG (chunk {ctype!r} cut short)")
        chunks.append((ctype, pos + 8, end))
        if ctype == b"IEND":
            return chunks
        pos = end + 4


def _png_chunk(path: Path, wanted: bytes) -> bytes | None:
    """The data of a PNG file's first chunk of type ``wanted``, or None."""
    data = path.read_bytes()
    for ctype, start, end in _png_chunks(data, path):
        if ctype == wanted:
            return data[start:end]
    return None


def _png_structure(data: bytes, path: Path) -> FrameInfo:
    chunks = _png_chunks(data, path)
    ctype, start, _end = chunks[0]
    if ctype != b"IHDR":
        raise InputError(f"{path}: corrupt PNG (first chunk is {ctype!r}, not IHDR)")
    cols, rows, _depth, colour = struct.unpack(">IIBB", data[start : start + 10])
    if colour not in _PNG_CHANNELS:
        raise InputError(f"{path}: corrupt PNG (colour type {colour})")
    return FrameInfo(rows, cols, _PNG_CHANNELS[colour])


def frame_info(path: str | Path) -> FrameInfo:
    """Shape of the frame :func:`read_frame` would return, from the header only.

    Used to check that all frames of a stack have one size before decoding any.
    JPEG/PNG structure is checked completely (truncated files are refused here
    too); TIFF and RAW headers are read by tifffile and LibRaw without decoding
    pixels, so a truncated TIFF or RAW file is only refused by :func:`read_frame`.
    RAW sizes are LibRaw's output size (``sizes.height x sizes.width``).
    """
    p = _existing(path)
    kind = _kind(p)
    if kind == "raw":
        try:
            with rawpy.imread(str(p)) as raw:
                sizes = raw.sizes
        except rawpy.LibRawError as err:
            raise _raw_error(p, err) from err
        return FrameInfo(sizes.height, sizes.width, 3)
    if kind == "tiff":
        try:
            with tifffile.TiffFile(p) as tif:
                rows, cols, channels = _tiff_page_info(_first_tiff_page(tif, p), p)
        except InputError:
            raise
        except (tifffile.TiffFileError, OSError, ValueError, struct.error) as err:
            raise InputError(f"{p}: cannot read TIFF ({type(err).__name__}: {err})") from err
        return FrameInfo(rows, cols, channels)
    data = p.read_bytes()
    if kind == "png":
        return _png_structure(data, p)
    layout = _jpeg_structure(data, p)
    return FrameInfo(layout.rows, layout.cols, 1 if layout.components == 1 else 3)


RAW_EXTENSIONS = frozenset(
    ".3fr .ari .arw .bay .cr2 .cr3 .crw .dcr .dcs .dng .erf .fff .iiq .k25 .kc2 .kdc "
    ".mdc .mef .mos .mrw .nef .nrw .orf .pef .raf .raw .rw2 .rwl .sr2 .srf .srw .x3f".split()
)
TIFF_EXTENSIONS = frozenset({".tif", ".tiff"})
PNG_EXTENSIONS = frozenset({".png"})
JPEG_EXTENSIONS = frozenset({".jpg", ".jpeg", ".jpe"})
IMAGE_EXTENSIONS = RAW_EXTENSIONS | TIFF_EXTENSIONS | PNG_EXTENSIONS | JPEG_EXTENSIONS


def _kind(path: Path) -> str:
    ext = path.suffix.lower()
    for kind, exts in (
        ("raw", RAW_EXTENSIONS),
        ("tiff", TIFF_EXTENSIONS),
        ("png", PNG_EXTENSIONS),
        ("jpeg", JPEG_EXTENSIONS),
    ):
        if ext in exts:
            return kind
    raise InputError(
        f"{path}: unsupported image extension {path.suffix!r}; supported: {supported_extensions()}"
    )


def _existing(path: str | Path) -> Path:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such image file")
    return p


def _raw_error(path: Path, err: Exception) -> InputError:
    detail = err.args[0] if err.args else ""
    if isinstance(detail, bytes):
        detail = detail.decode(errors="replace")
    return InputError(
        f"{path}: LibRaw cannot decode it ({type(err).__name__}: {detail}); the file is "
        "truncated, corrupt or not a RAW format LibRaw supports"
    )


def _first_tiff_page(tif: tifffile.TiffFile, path: Path) -> tifffile.TiffPage:
    """The first page of a TIFF-structured file (TIFF, NEF, CR2, DNG, ...).

    libtiff writes the image directory after the pixels, so a file cut short (a copy
    not finished, a card pulled out) has none; tifffile then raises IndexError.
    """
    try:
        return tif.pages.first
    except IndexError:
        raise InputError(
            f"{path}: truncated TIFF (no image directory: cut short, or still "
            "being copied?); copy it again"
        ) from None


def _tiff_page_info(page: tifffile.TiffPage, path: Path) -> tuple[int, int, int]:
    size = page.parent.filehandle.size
    ends = [o + n for o, n in zip(page.dataoffsets, page.databytecounts, strict=False)]
    if ends and max(ends) > size:
        raise InputError(
            f"{path}: truncated TIFF (its pixels end at byte {max(ends)}, the file at {size}); "
            "copy it again"
        )
    axes, shape = page.axes, page.shape
    if axes == "YX":
        return shape[0], shape[1], 1
    if axes in ("YXS", "SYX"):
        samples = shape[2] if axes == "YXS" else shape[0]
        rows, cols = (shape[0], shape[1]) if axes == "YXS" else (shape[1], shape[2])
        return rows, cols, (1 if samples <= 2 else 3)
    raise InputError(f"{path}: unsupported TIFF layout, axes {axes!r} shape {shape}")



def supported_extensions() -> str:
    """The readable extensions, for error messages."""
    return " ".join(sorted(IMAGE_EXTENSIONS))
