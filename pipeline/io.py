"""Reading and writing images: RAW, TIFF, PNG, JPEG <-> float32 linear light.

Every frame enters the pipeline as float32 linear light, shape ``(rows, cols)``
or ``(rows, cols, 3)`` (DESIGN.md, units). The weighted average of Sec. 9 and
the integrated PSF of Eqs. 5-7 are sums of *radiance*, so frames must be
linear before they are averaged:

* RAW files (whatever LibRaw reads: DNG, CR2, CR3, NEF, ARW, KDC, ...) are
  demosaiced by LibRaw with a unit gamma, no auto-brightening and a fixed white
  level, 16 bit, camera white balance, into linear sRGB primaries, then divided
  by 65535: a value of 1 is the white level and 0 the black level of the green
  channel ((raw - black) / (white - black)); red and blue carry the white
  balance gains. LibRaw clips each channel at the white level after white
  balance (highlight mode "clip"), so saturated highlights are not linear.
* Integer TIFF, PNG and JPEG code values are sRGB-encoded and are linearised
  with the exact piecewise sRGB EOTF (IEC 61966-2-1). Float TIFFs are linear.
  A 16-bit TIFF written by :func:`write_image` with ``encoding="linear16"`` is
  marked as linear in its ImageDescription and is read back as linear.
* Pixels are returned as stored: EXIF orientation is not applied (RAW is
  decoded in sensor orientation), so all frames of one camera line up. An alpha
  channel is dropped; multi-page TIFFs give their first page.

Writers encode linear float images; integer formats clip to [0, 1] at encoding
(the fraction clipped is logged), float32 TIFF is written unclipped. Every
write is atomic: a temporary file in the target directory, then ``os.replace``.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import json
import logging
import os
import re
import struct
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import rawpy
import tifffile

from pipeline.errors import InputError

log = logging.getLogger(__name__)

RAW_EXTENSIONS = frozenset(
    ".3fr .ari .arw .bay .cr2 .cr3 .crw .dcr .dcs .dng .erf .fff .iiq .k25 .kc2 .kdc "
    ".mdc .mef .mos .mrw .nef .nrw .orf .pef .raf .raw .rw2 .rwl .sr2 .srf .srw .x3f".split()
)
TIFF_EXTENSIONS = frozenset({".tif", ".tiff"})
PNG_EXTENSIONS = frozenset({".png"})
JPEG_EXTENSIONS = frozenset({".jpg", ".jpeg", ".jpe"})
IMAGE_EXTENSIONS = RAW_EXTENSIONS | TIFF_EXTENSIONS | PNG_EXTENSIONS | JPEG_EXTENSIONS

# write_image: allowed encodings per extension, the first one is the default.
WRITE_ENCODINGS = {
    ".tif": ("srgb16", "linear16", "float32", "srgb8"),
    ".tiff": ("srgb16", "linear16", "float32", "srgb8"),
    ".png": ("srgb8", "srgb16"),
    ".jpg": ("srgb8",),
    ".jpeg": ("srgb8",),
}
JPEG_QUALITY = 95

_TIFF_MARK = "flexdof transfer={}"
_TIFF_MARK_RE = re.compile(r"flexdof transfer=(srgb|linear)")
_EXIF_HEADER = b"Exif\x00\x00"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers carry the image size (C4 DHT, C8 JPG, CC DAC are not SOFs).
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def supported_extensions() -> str:
    """The readable extensions, for error messages."""
    return " ".join(sorted(IMAGE_EXTENSIONS))


# --- sRGB transfer functions (IEC 61966-2-1) -------------------------------------------------


def _float_dtype(x: np.ndarray) -> np.dtype:
    return np.dtype(np.float32) if x.dtype == np.float32 else np.dtype(np.float64)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """The exact sRGB EOTF: encoded values in [0, 1] -> linear light.

    ``c / 12.92`` for ``c <= 0.04045``, else ``((c + 0.055) / 1.055) ** 2.4``.
    Values outside [0, 1] follow the same formulas (no clipping). float32 in ->
    float32 out, anything else -> float64.
    """
    c = np.asarray(encoded)
    dtype = _float_dtype(c)
    c = c.astype(dtype, copy=False)
    high = ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(c <= 0.04045, c / 12.92, high).astype(dtype, copy=False)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The exact inverse sRGB EOTF: linear light -> encoded values.

    ``12.92 l`` for ``l <= 0.0031308``, else ``1.055 l ** (1/2.4) - 0.055``.
    No clipping; float32 in -> float32 out, anything else -> float64.
    """
    lin = np.asarray(linear)
    dtype = _float_dtype(lin)
    lin = lin.astype(dtype, copy=False)
    base = np.maximum(lin, dtype.type(0.0031308))
    if base.ndim >= 1 and base.size:  # cv2.pow: SIMD, same result as numpy to 1 ulp
        out = cv2.pow(np.ascontiguousarray(base.reshape(-1, base.shape[-1])), 1 / 2.4)
        out = out.reshape(base.shape)
    else:
        out = np.array(np.power(base, dtype.type(1 / 2.4)), dtype=dtype)
    out *= dtype.type(1.055)  # in place: this runs on every written image
    out -= dtype.type(0.055)
    low = lin <= 0.0031308
    out[low] = dtype.type(12.92) * lin[low]
    return out


@functools.cache
def _decode_lut(bits: int, transfer: str) -> np.ndarray:
    """float32 value of every integer code of a ``bits``-bit encoding."""
    codes = np.arange(2**bits, dtype=np.float64) / (2**bits - 1)
    table = srgb_to_linear(codes) if transfer == "srgb" else codes
    table = table.astype(np.float32)
    table.setflags(write=False)
    return table


def _decode_codes(codes: np.ndarray, transfer: str, path: Path) -> np.ndarray:
    """Integer code values (uint8/uint16) or floats -> float32 linear light."""
    if codes.dtype == np.uint8:
        return cv2.LUT(codes, _decode_lut(8, transfer).reshape(1, 256))  # 3x faster than take
    if codes.dtype == np.uint16:
        return _decode_lut(16, transfer)[codes]
    if codes.dtype.kind == "f":
        out = codes.astype(np.float32)
        return srgb_to_linear(out) if transfer == "srgb" else out
    raise InputError(
        f"{path}: unsupported sample type {codes.dtype} (supported: 8- and 16-bit "
        "integers, float); convert the file to 16-bit or float TIFF"
    )


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


def read_frame(path: str | Path, *, transfer: str | None = None) -> np.ndarray:
    """Read one image as float32 linear light.

    Parameters
    ----------
    path : str or Path
        A RAW file (anything LibRaw reads), TIFF, PNG or JPEG; the format is
        chosen by the extension.
    transfer : {"srgb", "linear"}, optional
        Override the transfer function of integer TIFF/PNG/JPEG code values
        (default: sRGB, or what a flexdof TIFF says). Ignored for RAW.

    Returns
    -------
    ndarray
        float32, ``(rows, cols)`` or ``(rows, cols, 3)``, linear light with
        white at 1 (see the module notes for RAW normalisation).

    Raises
    ------
    InputError
        Missing, truncated, corrupt or unsupported files, naming the file.
    """
    p = _existing(path)
    if transfer not in (None, "srgb", "linear"):
        raise InputError(f"transfer must be 'srgb', 'linear' or None, got {transfer!r}")
    kind = _kind(p)
    if kind == "raw":
        return _read_raw(p)
    if kind == "tiff":
        image = _read_tiff(p, transfer)
        bad = int(np.count_nonzero(~np.isfinite(image)))
        if bad:  # float TIFFs can hold NaN/inf; nothing downstream can use them
            raise InputError(f"{p}: {bad} pixel values are NaN or infinite; fix or drop this frame")
        return image
    return _read_codec(p, kind, transfer or "srgb")


def read_preview(path: str | Path, max_side_px: int) -> np.ndarray:
    """A reduced grey copy (float32 linear light, longest side ``max_side_px``) of a frame.

    JPEGs are decoded at 1/2, 1/4 or 1/8 scale in the DCT domain (much cheaper than
    a full decode); other formats are decoded fully and reduced with area
    averaging. The geometry is that of ``cv2.resize`` of the full frame.
    """
    p = _existing(path)
    if max_side_px < 1:
        raise InputError(f"max_side_px must be >= 1, got {max_side_px!r}")
    info = frame_info(p)
    full_side = max(info.rows, info.cols)
    image = None
    if _kind(p) == "jpeg" and full_side > max_side_px:
        factor = max((r for r in (1, 2, 4, 8) if full_side / r >= max_side_px), default=1)
        flags = {
            1: cv2.IMREAD_COLOR,
            2: cv2.IMREAD_REDUCED_COLOR_2,
            4: cv2.IMREAD_REDUCED_COLOR_4,
            8: cv2.IMREAD_REDUCED_COLOR_8,
        }[factor]
        data = p.read_bytes()
        _jpeg_structure(data, p)
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
        if decoded is None:
            raise InputError(f"{p}: OpenCV cannot decode it (corrupt JPEG data)")
        image = _decode_codes(_to_rgb(decoded, p, bgr=True), "srgb", p)
    if image is None:
        image = read_frame(p)
    grey = image.mean(axis=-1, dtype=np.float32) if image.ndim == 3 else image
    scale = min(1.0, max_side_px / full_side)
    size = (max(1, round(info.cols * scale)), max(1, round(info.rows * scale)))
    if grey.shape[::-1] != size:
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(grey, dtype=np.float32)


def _raw_error(path: Path, err: Exception) -> InputError:
    detail = err.args[0] if err.args else ""
    if isinstance(detail, bytes):
        detail = detail.decode(errors="replace")
    return InputError(
        f"{path}: LibRaw cannot decode it ({type(err).__name__}: {detail}); the file is "
        "truncated, corrupt or not a RAW format LibRaw supports"
    )


def _read_raw(path: Path) -> np.ndarray:
    try:
        with rawpy.imread(str(path)) as raw:
            rgb16 = raw.postprocess(
                gamma=(1, 1),  # linear output curve
                no_auto_bright=True,
                adjust_maximum_thr=0.0,  # keep the file's white level, never the data maximum
                use_camera_wb=True,
                output_bps=16,
                output_color=rawpy.ColorSpace.sRGB,
                user_flip=0,  # sensor orientation, like the other formats
            )
            image = rgb16.astype(np.float32)  # a copy: nothing refers to LibRaw's memory
    except rawpy.LibRawError as err:
        raise _raw_error(path, err) from err
    image /= np.float32(65535)
    return image


def _tiff_transfer(page: tifffile.TiffPage, transfer: str | None) -> str:
    if transfer is not None:
        return transfer
    if page.dtype is not None and page.dtype.kind == "f":
        return "linear"
    mark = _TIFF_MARK_RE.search(page.description or "")
    return mark.group(1) if mark else "srgb"


def _to_rgb(image: np.ndarray, path: Path, *, bgr: bool) -> np.ndarray:
    """(rows, cols[, c]) with c in 1..4 -> (rows, cols) or (rows, cols, 3); drops alpha."""
    if image.ndim == 3 and image.shape[2] in (1, 2):  # grey, grey + alpha
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        image = image[:, :, 2::-1] if bgr else image[:, :, :3]
    elif image.ndim != 2:
        raise InputError(
            f"{path}: unsupported image layout {image.shape} (expected grey or RGB[A])"
        )
    return np.ascontiguousarray(image)


def _tiff_page_info(page: tifffile.TiffPage, path: Path) -> tuple[int, int, int]:
    axes, shape = page.axes, page.shape
    if axes == "YX":
        return shape[0], shape[1], 1
    if axes in ("YXS", "SYX"):
        samples = shape[2] if axes == "YXS" else shape[0]
        rows, cols = (shape[0], shape[1]) if axes == "YXS" else (shape[1], shape[2])
        return rows, cols, (1 if samples <= 2 else 3)
    raise InputError(f"{path}: unsupported TIFF layout, axes {axes!r} shape {shape}")


def _read_tiff(path: Path, transfer: str | None) -> np.ndarray:
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages.first
            _tiff_page_info(page, path)
            data = page.asarray()
            mode = _tiff_transfer(page, transfer)
            axes = page.axes
    except (tifffile.TiffFileError, OSError, ValueError, struct.error) as err:
        raise InputError(f"{path}: cannot read TIFF ({type(err).__name__}: {err})") from err
    if axes == "SYX":
        data = np.moveaxis(data, 0, -1)
    return _decode_codes(_to_rgb(data, path, bgr=False), mode, path)


def _read_codec(path: Path, kind: str, transfer: str) -> np.ndarray:
    data = path.read_bytes()
    if kind == "jpeg":
        _jpeg_structure(data, path)
    else:
        _png_structure(data, path)
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as err:
        raise InputError(f"{path}: OpenCV cannot decode it: {err}") from err
    if image is None:
        raise InputError(f"{path}: OpenCV cannot decode it (corrupt {kind.upper()} data)")
    return _decode_codes(_to_rgb(image, path, bgr=True), transfer, path)


@dataclasses.dataclass(frozen=True)
class _JpegLayout:
    rows: int
    cols: int
    components: int
    exif: bytes | None


def _jpeg_structure(data: bytes, path: Path) -> _JpegLayout:
    """Walk the JPEG markers: size, components and EXIF; refuse truncated files.

    Entropy-coded data escapes 0xFF as 0xFF00, so after the first SOS the only
    0xFFD9 is the EOI marker; a file without it was cut short.
    """
    if not data.startswith(b"\xff\xd8"):
        raise InputError(f"{path}: not a JPEG file (no SOI marker 0xFFD8 at the start)")
    pos, size, exif = 2, None, None
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
        elif marker == 0xDA:  # start of scan: the entropy-coded data follows
            if size is None:
                raise InputError(f"{path}: corrupt JPEG (no SOF marker before the scan)")
            if data.find(b"\xff\xd9", pos + 2 + length) < 0:
                raise InputError(
                    f"{path}: truncated JPEG (no EOI marker 0xFFD9 after the image data: "
                    "the file was cut short); re-copy or re-export the file"
                )
            return _JpegLayout(size[0], size[1], size[2], exif)
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
                rows, cols, channels = _tiff_page_info(tif.pages.first, p)
        except (tifffile.TiffFileError, OSError, ValueError, struct.error) as err:
            raise InputError(f"{p}: cannot read TIFF ({type(err).__name__}: {err})") from err
        return FrameInfo(rows, cols, channels)
    data = p.read_bytes()
    if kind == "png":
        return _png_structure(data, p)
    layout = _jpeg_structure(data, p)
    return FrameInfo(layout.rows, layout.cols, 1 if layout.components == 1 else 3)


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
        data = p.read_bytes()
        for ctype, start, end in _png_chunks(data, p):
            if ctype == b"eXIf":
                return _EXIF_HEADER + data[start:end]
    return None


_SUBJECT_DISTANCE = 0x9206  # EXIF SubjectDistance, RATIONAL, metres
_EXIF_IFD = 0x8769


def subject_distance_mm(path: str | Path) -> float | None:
    """EXIF SubjectDistance in mm (``math.inf`` for infinity), or None if absent or 0.

    JPEG/PNG via their EXIF block; TIFF and TIFF-based RAW files (DNG, CR2,
    NEF, ARW, ...) via tifffile's EXIF IFD; other RAW containers give None.
    """
    p = _existing(path)
    kind = _kind(p)
    if kind in ("jpeg", "png"):
        block = read_exif(p)
        if block is None:
            return None
        from PIL import Image  # pillow parses EXIF; it is a dependency of matplotlib

        exif = Image.Exif()
        exif.load(block)
        value = exif.get_ifd(_EXIF_IFD).get(_SUBJECT_DISTANCE)
        rational = None if value is None else (value.numerator, value.denominator)
    else:
        try:
            with tifffile.TiffFile(p) as tif:
                tag = tif.pages.first.tags.get("ExifTag")
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


# --- writing ---------------------------------------------------------------------------------

_UMASK = os.umask(0)
os.umask(_UMASK)


def _atomic_write_bytes(path: Path, payload: bytes) -> None:
    """Write ``payload`` to a temporary file beside ``path``, then ``os.replace`` it."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise InputError(f"{path}: cannot write here ({err})") from err
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException as err:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise InputError(f"{path}: cannot write it ({err})") from err
        raise


def _json_default(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def write_json(path: str | Path, obj: object) -> None:
    """Write ``obj`` as indented JSON, atomically (numpy values and Paths allowed).

    NaN and infinities are refused (JSON has none): :class:`InputError`.
    """
    p = Path(path)
    try:
        text = json.dumps(obj, indent=2, allow_nan=False, default=_json_default)
    except (TypeError, ValueError) as err:
        raise InputError(f"{p}: cannot encode the result as JSON: {err}") from err
    _atomic_write_bytes(p, (text + "\n").encode("utf-8"))


def _quantise(image: np.ndarray, bits: int, transfer: str, path: Path) -> np.ndarray:
    """Clip to [0, 1] (logged), encode and round to ``bits``-bit integers."""
    clipped = np.clip(image, 0.0, 1.0)
    outside = int(np.count_nonzero(clipped != image))
    if outside:
        log.info("%s: clipped %d of %d values to [0, 1] for encoding", path, outside, image.size)
    if transfer == "srgb":
        clipped = linear_to_srgb(clipped)
    top = 2**bits - 1
    return np.rint(clipped * top).astype(np.uint8 if bits == 8 else np.uint16)


def _check_image(image: np.ndarray, path: Path) -> np.ndarray:
    arr = np.asarray(image)
    if arr.dtype.kind != "f":
        raise InputError(
            f"{path}: write_image expects float linear light, got dtype {arr.dtype}; "
            "convert with astype(np.float32) and scale to [0, 1]"
        )
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)) or 0 in arr.shape:
        raise InputError(f"{path}: image shape {arr.shape} is not (rows, cols) or (rows, cols, 3)")
    if not np.all(np.isfinite(arr)):
        raise InputError(
            f"{path}: image contains {int(np.count_nonzero(~np.isfinite(arr)))} NaN/Inf "
            "values; fix the computation (nothing was written)"
        )
    return arr


def _insert_jpeg_exif(jpeg: bytes, exif: bytes, path: Path) -> bytes:
    """Insert an APP1 EXIF segment after SOI (and after a JFIF APP0 if there is one)."""
    block = exif if exif.startswith(_EXIF_HEADER) else _EXIF_HEADER + exif
    if len(block) + 2 > 0xFFFF:
        raise InputError(f"{path}: EXIF block of {len(block)} bytes is too large for JPEG APP1")
    pos = 2
    if jpeg[2:4] == b"\xff\xe0":
        pos += 2 + struct.unpack(">H", jpeg[4:6])[0]
    segment = b"\xff\xe1" + struct.pack(">H", len(block) + 2) + block
    return jpeg[:pos] + segment + jpeg[pos:]


def _insert_png_exif(png: bytes, exif: bytes, path: Path) -> bytes:
    """Insert an eXIf chunk before the first IDAT chunk."""
    body = exif.removeprefix(_EXIF_HEADER)
    for ctype, start, _end in _png_chunks(png, path):
        if ctype == b"IDAT":
            pos = start - 8
            break
    chunk = struct.pack(">I", len(body)) + b"eXIf" + body
    chunk += struct.pack(">I", zlib.crc32(b"eXIf" + body) & 0xFFFFFFFF)
    return png[:pos] + chunk + png[pos:]


def write_image(
    path: str | Path,
    image: np.ndarray,
    *,
    encoding: str | None = None,
    exif: bytes | None = None,
) -> None:
    """Encode a float linear-light image and write it atomically.

    Parameters
    ----------
    path : str or Path
        Output file; the format comes from the extension (.tif/.tiff, .png,
        .jpg/.jpeg).
    image : ndarray
        Float linear light, ``(rows, cols)`` or ``(rows, cols, 3)``; NaN/Inf
        are refused.
    encoding : str, optional
        TIFF: ``"srgb16"`` (default), ``"linear16"``, ``"float32"`` (linear,
        unclipped) or ``"srgb8"``; PNG: ``"srgb8"`` (default) or ``"srgb16"``;
        JPEG: ``"srgb8"`` (quality 95).
    exif : bytes, optional
        An EXIF block as :func:`read_exif` returns it; carried into JPEG (APP1)
        and PNG (eXIf). TIFF output does not carry it (logged).

    Notes
    -----
    Integer encodings clip to [0, 1] (the number of clipped values is logged
    at INFO) and round to the nearest code. The file is written to a
    temporary file in the same directory and renamed over ``path``, so on any
    error no partial file is left and an existing file stays intact.
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in WRITE_ENCODINGS:
        raise InputError(
            f"{p}: cannot write extension {p.suffix!r}; use one of {', '.join(WRITE_ENCODINGS)}"
        )
    allowed = WRITE_ENCODINGS[ext]
    enc = allowed[0] if encoding is None else encoding
    if enc not in allowed:
        raise InputError(
            f"{p}: encoding {encoding!r} is not available for {ext}; "
            f"use one of {', '.join(allowed)}"
        )
    arr = _check_image(image, p)
    bits = 8 if enc == "srgb8" else 16
    if ext in TIFF_EXTENSIONS:
        if enc == "float32":
            data, transfer = arr.astype(np.float32), "linear"
        else:
            transfer = "linear" if enc == "linear16" else "srgb"
            data = _quantise(arr, bits, transfer, p)
        if exif is not None:
            log.info("%s: EXIF is not carried into TIFF output", p)
        buffer = io.BytesIO()
        tifffile.imwrite(
            buffer,
            data,
            photometric="rgb" if data.ndim == 3 else "minisblack",
            description=_TIFF_MARK.format(transfer),
            software="flexdof",
            metadata=None,
        )
        payload = buffer.getvalue()
    else:
        codes = _quantise(arr, bits, "srgb", p)
        if codes.ndim == 3:
            codes = np.ascontiguousarray(codes[:, :, ::-1])  # RGB -> BGR for OpenCV
        params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if ext in JPEG_EXTENSIONS else []
        try:
            ok, encoded = cv2.imencode(ext, codes, params)
        except cv2.error as err:
            raise InputError(f"{p}: OpenCV cannot encode the image: {err}") from err
        if not ok:
            raise InputError(f"{p}: OpenCV cannot encode a {arr.shape} image as {ext}")
        payload = encoded.tobytes()
        if exif is not None:
            insert = _insert_jpeg_exif if ext in JPEG_EXTENSIONS else _insert_png_exif
            payload = insert(payload, exif, p)
    _atomic_write_bytes(p, payload)
