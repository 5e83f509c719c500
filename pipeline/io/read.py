"""Reading and writing images: RAW, TIFF, PNG, JPEG <-> float32 linear light.

Every frame enters the pipeline as float32 linear light, shape ``(rows, cols)``
or ``(rows, cols, 3)`` (docs/formats.md, units). The weighted average of Sec. 9 and
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
  decoded in sensor orientation, reduced JPEG decodes too), so all frames of one camera
  line up; the result is turned upright when written (:mod:`pipeline.io.orientation`). An alpha
  channel is dropped; multi-page TIFFs give their first page.

Writers encode linear float images; integer formats clip to [0, 1] at encoding
(the fraction clipped is logged), float32 TIFF is written unclipped. Every
write is atomic: a temporary file in the target directory, then ``os.replace``.
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import struct
import sys
import tempfile
import threading
from pathlib import Path

import cv2
import numpy as np
import tifffile

from pipeline.core.colour import srgb_to_linear
from pipeline.errors import InputError
from pipeline.io.probe import (
    _existing,
    _first_tiff_page,
    _jpeg_structure,
    _kind,
    _png_structure,
    _raw_error,
    _tiff_page_info,
    frame_info,
)

_TIFF_MARK_RE = re.compile(r"flexdof transfer=(srgb|linear)")


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


def read_frame(
    path: str | Path, *, transfer: str | None = None, white: float | None = None
) -> np.ndarray:
    """Read one image as float32 linear light.

    Parameters
    ----------
    path : str or Path
        A RAW file (anything LibRaw reads), TIFF, PNG or JPEG; the format is
        chosen by the extension.
    transfer : {"srgb", "linear"}, optional
        Override the transfer function of integer TIFF/PNG/JPEG code values
        (default: sRGB, or what a flexdof TIFF says). Ignored for RAW.
    white : float, optional
        The value of white in a float TIFF (default 1): its samples are divided by it,
        so frames in other units (counts of a 12-bit sensor, 0-65535) come out with
        white at 1 like every other format. Only float TIFFs take it: the white of
        integer codes is their largest code and RAW files carry their own.

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
    if white is not None and not (np.isfinite(white) and white > 0):
        raise InputError(f"white must be a finite number > 0, got {white!r}")
    kind = _kind(p)
    if white is not None and kind != "tiff":
        raise InputError(_white_for_codes(p, f"{kind.upper()} file"))
    if kind == "raw":
        return _read_raw(p)
    if kind == "tiff":
        image = _read_tiff(p, transfer, white)
        bad = int(np.count_nonzero(~np.isfinite(image)))
        if bad:  # float TIFFs can hold NaN/inf; nothing downstream can use them
            raise InputError(f"{p}: {bad} pixel values are NaN or infinite; fix or drop this frame")
        return image
    return _read_codec(p, kind, transfer or "srgb")


def _white_for_codes(path: Path, what: str) -> str:
    return (
        f"{path}: a white level (--white, or white in stack.toml) applies to float TIFF "
        f"frames only, and this is a {what}, whose white is its largest code (RAW: its "
        "own white level); drop the white level for these frames"
    )


def read_preview(path: str | Path, max_side_px: int, *, white: float | None = None) -> np.ndarray:
    """A reduced grey copy (float32 linear light, longest side ``max_side_px``) of a frame.

    JPEGs are decoded at 1/2, 1/4 or 1/8 scale in the DCT domain (much cheaper than
    a full decode), RAW files at half size (each 2x2 Bayer block one pixel, without
    demosaicing: 0.05 against 0.24 s for an 1734x1156 DNG) when the preview is at most
    half the frame; other formats are decoded fully. Then they are reduced with area
    averaging. The geometry is that of ``cv2.resize`` of the full frame. ``white``: as
    for :func:`read_frame`.
    """
    p = _existing(path)
    if max_side_px < 1:
        raise InputError(f"max_side_px must be >= 1, got {max_side_px!r}")
    info = frame_info(p)
    full_side = max(info.rows, info.cols)
    image = None
    if _kind(p) == "jpeg" and full_side > max_side_px and white is None:
        factor = max((r for r in (1, 2, 4, 8) if full_side / r >= max_side_px), default=1)
        flags = {
            1: cv2.IMREAD_COLOR,
            2: cv2.IMREAD_REDUCED_COLOR_2,
            4: cv2.IMREAD_REDUCED_COLOR_4,
            8: cv2.IMREAD_REDUCED_COLOR_8,
        }[factor]
        data = p.read_bytes()
        _jpeg_structure(data, p)
        # as stored, as read_frame decodes it (a reduced decode applies the EXIF orientation)
        decoded = _imdecode_jpeg(data, flags | cv2.IMREAD_IGNORE_ORIENTATION, p)
        if decoded is None:
            raise InputError(f"{p}: OpenCV cannot decode it (corrupt JPEG data)")
        image = _decode_codes(_to_rgb(decoded, p, bgr=True), "srgb", p)
    if _kind(p) == "raw" and full_side >= 2 * max_side_px and white is None:
        image = _read_raw(p, half_size=True)
    if image is None:
        image = read_frame(p, white=white)
    if image.ndim == 3:  # (r + g) + b, then / 3: numpy's float32 mean, without its copies
        grey = np.add(image[..., 0], image[..., 1], dtype=np.float32)
        grey += image[..., 2]
        grey /= np.float32(3)
    else:
        grey = image
    scale = min(1.0, max_side_px / full_side)
    size = (max(1, round(info.cols * scale)), max(1, round(info.rows * scale)))
    if grey.shape[::-1] != size:
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(grey, dtype=np.float32)


# libjpeg reports corrupt entropy-coded data only as a warning on stderr (OpenCV then
# returns an image with garbage blocks): JPEGs decode with fd 2 captured, and such a
# warning becomes an error naming the file. Decoders share one capture window, so frames
# decode side by side (one at a time, the window serialised the accumulation's reads);
# a warning seen while several decoded is pinned on its file by decoding the suspects
# again, each alone in its own window.
_JPEG_FATAL = ("Corrupt JPEG data", "Premature end of JPEG", "Bogus", "Invalid JPEG")


class _StderrWindow:
    """fd 2 redirected to a temporary file while at least one decoder is inside.

    ``inside()`` yields a list that receives, on leaving, what was written to fd 2 while
    this decoder was inside (its own warnings and those of concurrent decoders). An
    ``exclusive`` entry waits until the window is empty and keeps others out (new
    entries wait while it waits). The last
    decoder to leave restores fd 2 and passes on every line that is not a JPEG warning
    (another thread's log output, say).
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._inside = 0
        self._exclusive = False
        self._waiting = 0  # exclusive entries waiting: they go first
        self._file = None
        self._saved = -1

    @contextlib.contextmanager
    def inside(self, exclusive: bool = False):
        with self._cond:
            self._waiting += exclusive
            while self._exclusive or (self._inside if exclusive else self._waiting):
                self._cond.wait()
            self._waiting -= exclusive
            self._exclusive = exclusive
            if self._inside == 0:
                sys.stderr.flush()
                self._file = tempfile.TemporaryFile()
                self._saved = os.dup(2)
                os.dup2(self._file.fileno(), 2)
            self._inside += 1
            fd = self._file.fileno()
            start = os.fstat(fd).st_size
        seen: list[str] = []
        try:
            yield seen
        finally:
            with self._cond:
                end = os.fstat(fd).st_size
                seen.append(os.pread(fd, end - start, start).decode("utf-8", errors="replace"))
                self._inside -= 1
                self._exclusive = False
                if self._inside == 0:
                    self._close(fd, end)
                self._cond.notify_all()

    def _close(self, fd: int, end: int) -> None:
        os.dup2(self._saved, 2)
        os.close(self._saved)
        text = os.pread(fd, end, 0).decode("utf-8", errors="replace")
        self._file.close()
        self._file = None
        for line in text.splitlines():
            if line.strip() and not _fatal(line):
                print(line.strip(), file=sys.stderr)


def _fatal(line: str) -> bool:
    return line.strip().startswith(_JPEG_FATAL)


_STDERR_WINDOW = _StderrWindow()


def _imdecode_jpeg(data: bytes, flags: int, path: Path):
    buffer = np.frombuffer(data, np.uint8)
    exclusive = False
    while True:
        with _STDERR_WINDOW.inside(exclusive) as seen:
            image = cv2.imdecode(buffer, flags)
        fatal = [line.strip() for line in "".join(seen).splitlines() if _fatal(line)]
        if not fatal:
            return image
        if exclusive:
            raise InputError(
                f"{path}: corrupt JPEG data (libjpeg: {fatal[0]}); the decoded image would hold "
                "garbage blocks: re-copy or re-export the file"
            )
        exclusive = True  # this frame or one decoding beside it: decode it again alone


def _read_raw(path: Path, *, half_size: bool = False) -> np.ndarray:
    """A RAW file as linear float32 RGB; ``half_size``: each 2x2 Bayer block as one pixel
    (no demosaicing; LibRaw's fast path for reduced copies, about 5x faster)."""
    import rawpy  # only RAW frames need it (an import JPEG/TIFF stacks do not pay)

    try:
        with rawpy.imread(str(path)) as raw:
            rgb16 = raw.postprocess(
                half_size=half_size,
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


_CVT_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.float32))  # cvtColor's


def _to_rgb(image: np.ndarray, path: Path, *, bgr: bool) -> np.ndarray:
    """(rows, cols[, c]) with c in 1..4 -> (rows, cols) or (rows, cols, 3); drops alpha."""
    if image.ndim == 3 and image.shape[2] in (1, 2):  # grey, grey + alpha
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] in (3, 4):
        if image.dtype in _CVT_DTYPES and (bgr or image.shape[2] == 4):
            code = {
                (True, 3): cv2.COLOR_BGR2RGB,
                (True, 4): cv2.COLOR_BGRA2RGB,
                (False, 4): cv2.COLOR_RGBA2RGB,
            }[(bgr, image.shape[2])]
            return cv2.cvtColor(image, code)  # one pass, contiguous (a view + copy costs 8x)
        image = image[:, :, 2::-1] if bgr else image[:, :, :3]
    elif image.ndim != 2:
        raise InputError(
            f"{path}: unsupported image layout {image.shape} (expected grey or RGB[A])"
        )
    return np.ascontiguousarray(image)


def _tifffile_decodes(page: tifffile.TiffPage) -> bool:
    """Whether tifffile has a decoder for the page's compression and predictor.

    Without the optional imagecodecs package it decodes Deflate and PackBits but not
    LZW (what Photoshop, Lightroom and OpenCV write by default), JPEG or the
    floating-point predictor.
    """
    return page.compression in tifffile.TIFF.DECOMPRESSORS and (
        page.predictor in tifffile.TIFF.PREDICTORS
    )


# The codecs the OpenCV fallback is used for: those its libtiff decodes in every release
# (OpenCV 5.1's also claims WebP, and returns zeros for data it then fails to decode, with
# only a log line: other codecs get the one-line error instead). A failed JPEG or 16-bit
# LZW strip returns None; a corrupt 8-bit LZW strip comes back as zeros past the damage
# under 5.0 and 5.1 alike (libtiff's RGBA reader only logs it), which nothing here can see
OPENCV_TIFF_CODECS = frozenset(
    {
        tifffile.COMPRESSION.LZW,
        tifffile.COMPRESSION.JPEG,
        tifffile.COMPRESSION.ADOBE_DEFLATE,
        tifffile.COMPRESSION.DEFLATE,
    }
)


def _tiff_by_opencv(path: Path, page: tifffile.TiffPage, info: tuple[int, int, int]) -> np.ndarray:
    """The first page decoded by OpenCV's libtiff (LZW, JPEG, the float predictor), RGB;
    ``info`` is the page's ``(rows, cols, channels)`` by its tags."""
    codec = getattr(page.compression, "name", page.compression)
    data = None
    if page.compression in OPENCV_TIFF_CODECS:
        data = cv2.imdecode(np.frombuffer(path.read_bytes(), np.uint8), cv2.IMREAD_UNCHANGED)
    if data is None or data.dtype != page.dtype:
        predictor = getattr(page.predictor, "name", page.predictor)
        raise InputError(
            f"{path}: cannot decode its {codec} compression with predictor {predictor} "
            "(tifffile lacks the codec and OpenCV cannot read the file); save it "
            "uncompressed or with LZW or Deflate, or `pip install imagecodecs`"
        )
    # 8-bit RGBA goes through libtiff's RGBA interface, which multiplies the colour by an
    # unassociated alpha (16-bit and float are read as stored)
    rgba8 = data.dtype == np.uint8 and data.ndim == 3 and data.shape[2] == 4
    if rgba8 and data[..., 3].min() < 255:
        raise InputError(
            f"{path}: its alpha channel is not opaque, and OpenCV, which decodes this "
            "compression here, multiplies the colour by it; save it without alpha, "
            "uncompressed, or `pip install imagecodecs`"
        )
    image = _to_rgb(data, path, bgr=True)
    rows, cols, channels = info
    if image.shape[:2] != (rows, cols) or (image.ndim == 3) != (channels == 3):
        raise InputError(
            f"{path}: OpenCV decoded its {codec} data as {image.shape}, not the "
            f"{rows}x{cols} px, {channels} channel(s) its tags say; save it uncompressed "
            "or `pip install imagecodecs`"
        )
    return image


def _read_tiff(path: Path, transfer: str | None, white: float | None = None) -> np.ndarray:
    try:
        with tifffile.TiffFile(path) as tif:
            page = _first_tiff_page(tif, path)
            info = _tiff_page_info(page, path)
            mode = _tiff_transfer(page, transfer)
            decodes = _tifffile_decodes(page)
            if decodes:
                data = page.asarray()
                if page.axes == "SYX":
                    data = np.moveaxis(data, 0, -1)
    except InputError:
        raise
    except (tifffile.TiffFileError, OSError, ValueError, struct.error) as err:
        raise InputError(f"{path}: cannot read TIFF ({type(err).__name__}: {err})") from err
    if not decodes:
        data = _tiff_by_opencv(path, page, info)
    image = _decode_codes(_to_rgb(data, path, bgr=False), mode, path)
    if white is not None:
        if data.dtype.kind != "f":
            raise InputError(_white_for_codes(path, f"TIFF of {data.dtype.itemsize * 8}-bit codes"))
        image /= np.float32(white)
    return image


def _read_codec(path: Path, kind: str, transfer: str) -> np.ndarray:
    data = path.read_bytes()
    if kind == "jpeg":
        _jpeg_structure(data, path)
    else:
        _png_structure(data, path)
    try:
        if kind == "jpeg":
            image = _imdecode_jpeg(data, cv2.IMREAD_UNCHANGED, path)
        else:
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as err:
        raise InputError(f"{path}: OpenCV cannot decode it: {err}") from err
    if image is None:
        raise InputError(f"{path}: OpenCV cannot decode it (corrupt {kind.upper()} data)")
    return _decode_codes(_to_rgb(image, path, bgr=True), transfer, path)
