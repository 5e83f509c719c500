"""EXIF orientation: which way up a frame was shot, and the result turned that way.

A camera held upright for a portrait stores its pixels in the sensor's landscape
geometry and records in the EXIF ``Orientation`` tag (0x0112, TIFF tag 274) how a viewer
must turn them. The frames of a stack are decoded and aligned as stored
(:func:`pipeline.io.read.read_frame`): their pixels line up whatever their tags say (a
camera pointing straight down can flip its tag from frame to frame while its sensor does
not move). The result is turned upright as the stack's first frame says
(:func:`stack_orientation`) when it is written, as every viewer, OpenCV's ``imread`` and
focus-stack (which decodes with it) show the frames. A carried EXIF block then says
``Orientation = 1`` (:func:`upright_exif`), so no viewer turns it a second time.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import tifffile

from pipeline.io.exif import _ifd_entries, read_exif
from pipeline.io.probe import _EXIF_HEADER, _existing, _first_tiff_page, _kind, _raw_error

log = logging.getLogger(__name__)

_ORIENTATION = 0x0112
_SHORT = 3  # TIFF field type: unsigned 16-bit integer
UPRIGHT = 1
# EXIF code -> (quarter turns counter-clockwise, then a left-right mirror), what a viewer
# does to the stored pixels to show them upright (EXIF 2.32, Sec. 4.6.4 A, tag 0x0112)
_TURNS = {1: (0, False), 2: (0, True), 3: (2, False), 4: (2, True),
          5: (3, True), 6: (3, False), 7: (1, True), 8: (1, False)}  # fmt: skip
# LibRaw's ``sizes.flip`` (none, half turn, a quarter counter-clockwise, clockwise) as EXIF
_LIBRAW_FLIP = {0: 1, 3: 3, 5: 8, 6: 6}


def _orientation_field(tiff: bytes) -> tuple[str, int] | None:
    """The byte order and offset of IFD0's Orientation value in a TIFF structure, or None
    where it is absent, not one SHORT, or the structure is malformed."""
    order = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    if order is None:
        return None
    try:
        (ifd0,) = struct.unpack_from(order + "I", tiff, 4)
        (count,) = struct.unpack_from(order + "H", tiff, ifd0)
        entries = _ifd_entries(tiff, ifd0, order)
    except (struct.error, IndexError):
        return None
    field = entries.get(_ORIENTATION)
    if field is None or field[0] != _SHORT or field[1] != 1:
        return None
    tags = [struct.unpack_from(order + "H", tiff, ifd0 + 2 + 12 * i)[0] for i in range(count)]
    return order, ifd0 + 2 + 12 * tags.index(_ORIENTATION) + 8


def _block_orientation(block: bytes) -> int:
    """The Orientation of an EXIF block (``Exif\\0\\0`` + TIFF structure); 1 if absent."""
    tiff = block.removeprefix(_EXIF_HEADER)
    field = _orientation_field(tiff)
    if field is None:
        return UPRIGHT
    order, at = field
    return struct.unpack_from(order + "H", tiff, at)[0]


def exif_orientation(path: str | Path) -> int:
    """The EXIF orientation of a frame, 1-8 (1: stored upright).

    JPEG and PNG from their EXIF block, TIFF from IFD0's Orientation tag, RAW files (every
    format LibRaw reads) from LibRaw's ``flip``, which it takes from the maker's metadata
    (for DNG, IFD0's Orientation; a half or quarter turn only). Files without the tag and
    values outside 1-8 give 1: the pixels as stored.
    """
    p = _existing(path)
    kind = _kind(p)
    if kind in ("jpeg", "png"):
        block = read_exif(p)
        code = UPRIGHT if block is None else _block_orientation(block)
    elif kind == "raw":
        import rawpy  # only RAW frames need it

        try:
            with rawpy.imread(str(p)) as raw:
                code = _LIBRAW_FLIP.get(raw.sizes.flip, UPRIGHT)
        except rawpy.LibRawError as err:
            raise _raw_error(p, err) from err
    else:
        try:
            with tifffile.TiffFile(p) as tif:
                tag = _first_tiff_page(tif, p).tags.get("Orientation")
                code = UPRIGHT if tag is None else int(tag.value)
        except (tifffile.TiffFileError, struct.error, ValueError, TypeError):
            code = UPRIGHT  # unreadable here: read_frame names the file's problem
    return code if code in _TURNS else UPRIGHT


def stack_orientation(files: Sequence[str | Path]) -> int:
    """The orientation a stack's result is written in: its first frame's
    (:func:`exif_orientation`). Frames whose tag differs are named in a warning; their
    pixels are used as stored, which line up with the others'."""
    codes = [exif_orientation(f) for f in files]
    differ = [Path(f).name for f, c in zip(files, codes) if c != codes[0]]
    if differ:
        log.warning(
            "%d frame(s) carry another EXIF orientation than %s (%d), e.g. %s: the camera "
            "turned or pointed up or down; the frames are aligned as stored and the result "
            "is written as the first frame shows",
            len(differ), Path(files[0]).name, codes[0], ", ".join(differ[:3]),
        )  # fmt: skip
    return codes[0] if codes else UPRIGHT


def upright(image: np.ndarray, code: int) -> np.ndarray:
    """``image`` (rows, cols[, channels]) turned as a viewer shows a frame of EXIF
    orientation ``code``: 6 turns it a quarter clockwise, 8 counter-clockwise, 3 half
    way, 2 and 4 mirror it, 5 and 7 mirror it about a diagonal."""
    turns, mirror = _TURNS.get(code, (0, False))
    out = np.rot90(image, turns) if turns else image
    return np.ascontiguousarray(out[:, ::-1] if mirror else out)


def upright_exif(block: bytes | None) -> bytes | None:
    """``block`` (``Exif\\0\\0`` + TIFF structure) saying ``Orientation = 1``: the result's
    pixels are upright (:func:`upright`), and a viewer must not turn them again. A block
    without the tag is returned as it is."""
    if block is None:
        return None
    head = _EXIF_HEADER if block.startswith(_EXIF_HEADER) else b""
    tiff = bytearray(block[len(head) :])
    field = _orientation_field(bytes(tiff))
    if field is None:
        return block
    order, at = field
    struct.pack_into(order + "H", tiff, at, UPRIGHT)
    return head + bytes(tiff)
