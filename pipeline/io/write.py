"""Writing results atomically (temporary file + rename): images (16-bit sRGB or linear
TIFF, float32 TIFF, 8-bit PNG/JPEG) and JSON sidecars.
"""

from __future__ import annotations

import io
import json
import logging
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
import tifffile

from pipeline.core.colour import linear_to_srgb
from pipeline.errors import InputError
from pipeline.io.exif import _insert_jpeg_exif, _insert_png_exif
from pipeline.io.probe import JPEG_EXTENSIONS, TIFF_EXTENSIONS

log = logging.getLogger(__name__)

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


# --- writing ---------------------------------------------------------------------------------

_UMASK = os.umask(0)  # the process umask, read once (setting it is the only way to read it)
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
