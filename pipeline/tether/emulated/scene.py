"""The emulated camera's scene: two textured depth planes rendered by the project simulator.

:func:`render_frame` is the one entry point the emulator uses. It renders the
scene with :func:`pipeline.core.simulate.render.render` for a static capture at the motor's
image distance: defocus by the lens PSF (Eqs. 2-3), occlusion at the planes'
boundary, and the magnification ``p / p_ref`` (Sec. 3, 9) that focusing by
moving the lens relative to the detector causes (Sec. 8).
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.core.lens import Lens
from pipeline.core.optics import image_distance
from pipeline.core.scene import Camera, Scene
from pipeline.core.simulate.render import render

# Sigma 30 mm f/1.4 on an APS-C sensor binned ~11x to 320x224 pixels (fast to render).
LENS = Lens(
    focal_length_mm=30.0,
    f_number=1.4,
    pixel_pitch_um=70.0,
    width_px=320,
    height_px=224,
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


_LEFT = (np.arange(LENS.width_px) < LENS.width_px // 2)[None, :] * np.ones((LENS.height_px, 1))
SCENE = Scene.from_planes([(_texture(1), _LEFT, NEAR_MM), (_texture(2), 1.0 - _LEFT, FAR_MM)])


def render_frame(focus_step: float) -> np.ndarray:
    """Linear float32 image (224, 320) in [0.1, 0.9] with the focus at ``focus_step``.

    The left half is a plane at ``NEAR_MM``, the right half one at ``FAR_MM``;
    the simulator blurs each by the lens PSF for the image distance ``p`` of the
    motor position and magnifies the frame by ``p / p(0)`` about its centre.
    """
    camera = Camera.static(
        LENS, image_distance_at(focus_step), 0.01, reference_image_distance_mm=image_distance_at(0)
    )
    # the magnification resampling can overshoot by ~1e-5; the camera encodes [0, 1]
    return np.clip(render(SCENE, camera), 0.0, 1.0).astype(np.float32)


def encode_jpeg(image: np.ndarray) -> bytes:
    """8-bit sRGB JPEG of a linear image in [0, 1] (values outside are an error)."""
    _check_range(image)
    srgb = np.where(image <= 0.0031308, 12.92 * image, 1.055 * np.power(image, 1 / 2.4) - 0.055)
    ok, buf = cv2.imencode(
        ".jpg", np.round(srgb * 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 95]
    )
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
        raise ValueError(f"emulated frame outside [0, 1]: min {image.min()}, max {image.max()}")
