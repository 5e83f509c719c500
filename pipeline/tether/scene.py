"""The emulated camera's scene: two textured depth planes seen through a real lens model.

:func:`render_frame` is the one entry point the emulator uses (swap in the
project simulator here). Defocus uses :func:`pipeline.psf.lens_psf` (Eqs. 2-3)
and the magnification changes as ``p / p_ref`` (Sec. 3, 9) because focusing
moves the lens relative to the detector (Sec. 8).
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.optics import image_distance
from pipeline.profiles import Lens
from pipeline.psf import lens_psf

# Sigma 30 mm f/1.4 on an APS-C sensor binned ~11x to 320x224 pixels (fast to render).
LENS = Lens(
    focal_length_mm=30.0, f_number=1.4, pixel_pitch_um=70.0, width_px=320, height_px=224,
    name="emulated Sigma 30 mm f/1.4, APS-C binned to 320x224",
)
NEAR_MM, FAR_MM = 600.0, 1500.0  # depths of the left and right planes
UM_PER_STEP = 5.0  # image-distance change per focus-drive step (the truth calibration recovers)
P_START_MM = float(image_distance(LENS.focal_length_mm, NEAR_MM)) + 0.1  # motor step 0


def image_distance_at(focus_step: float) -> float:
    """Lens-to-detector distance p at a motor position (+ steps focus farther: p shrinks)."""
    return P_START_MM - focus_step * UM_PER_STEP * 1e-3


def _texture(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random((LENS.height_px, LENS.width_px)), (0, 0), 1.2)
    noise = (noise - noise.min()) / np.ptp(noise)
    x = np.arange(LENS.width_px)
    bars = 0.5 + 0.5 * np.sign(np.sin(x / (3.0 + seed)))[None, :]
    return (0.15 + 0.5 * noise + 0.2 * bars).astype(np.float64)


_PLANES = ((NEAR_MM, _texture(1)), (FAR_MM, _texture(2)))
_LEFT = (np.arange(LENS.width_px) < LENS.width_px // 2)[None, :].astype(np.float64)


def render_frame(focus_step: float) -> np.ndarray:
    """Linear float32 image (224, 320) in [0.1, 0.9] with the focus at ``focus_step``.

    The left half is a plane at ``NEAR_MM``, the right half one at ``FAR_MM``;
    each is blurred by the lens PSF for the image distance ``p`` of the motor
    position, and the frame is magnified by ``p / p(0)`` about its centre.
    """
    p = image_distance_at(focus_step)
    out = np.zeros((LENS.height_px, LENS.width_px))
    for (depth, texture), weight in zip(_PLANES, (_LEFT, 1.0 - _LEFT)):
        kernel = lens_psf(LENS, depth, p)
        out += weight * cv2.filter2D(texture, -1, kernel, borderType=cv2.BORDER_REFLECT)
    scale = p / image_distance_at(0)  # magnification relative to step 0
    cx, cy = (LENS.width_px - 1) / 2, (LENS.height_px - 1) / 2
    warp = np.array([[scale, 0, cx * (1 - scale)], [0, scale, cy * (1 - scale)]])
    # float32: OpenCV 5.0's cubic warpAffine zeroes the first rows of float64 images
    out = cv2.warpAffine(out.astype(np.float32), warp, (LENS.width_px, LENS.height_px),
                         flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return out


def encode_jpeg(image: np.ndarray) -> bytes:
    """8-bit sRGB JPEG of a linear image in [0, 1] (values outside are an error)."""
    _check_range(image)
    srgb = np.where(image <= 0.0031308, 12.92 * image, 1.055 * np.power(image, 1 / 2.4) - 0.055)
    ok, buf = cv2.imencode(".jpg", np.round(srgb * 255).astype(np.uint8),
                           [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise RuntimeError("OpenCV could not encode the emulated frame as JPEG")
    return buf.tobytes()


def encode_tiff16(image: np.ndarray) -> bytes:
    """Linear 16-bit TIFF of an image in [0, 1]."""
    import io

    import tifffile

    _check_range(image)
    out = io.BytesIO()
    tifffile.imwrite(out, np.round(image * 65535).astype(np.uint16))
    return out.getvalue()


def _check_range(image: np.ndarray) -> None:
    if not (np.all(np.isfinite(image)) and image.min() >= 0 and image.max() <= 1):
        raise ValueError(
            f"emulated frame outside [0, 1]: min {image.min()}, max {image.max()}"
        )
