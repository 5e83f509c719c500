"""Focus-step calibration: drive steps -> image distance, from a stack's magnification.

Focusing moves the lens relative to the detector, so a frame's scale relative
to the reference frame is ``p_i / p_ref`` (Sec. 3, 9; docs/formats.md). With
``p_ref`` from the lens law (Eq. 1) for the reference focus distance, each
frame gives ``p_i - p_ref = p_ref (s_i - 1)``; a least-squares line through the
reference against the frame's drive position gives mm per step.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.optics import image_distance
from pipeline.errors import InputError


def estimate_scale(reference: np.ndarray, image: np.ndarray, *, max_side: int = 320) -> float:
    """Magnification of ``image`` relative to ``reference`` (ECC, affine, downscaled copies).

    Returns ``s`` with ``image(c + s (x - c)) ~ reference(x)``: ``sqrt(|det A|)`` of
    the affine part found by ``cv2.findTransformECC``.
    """
    ref, img = (_gray_small(a, max_side) for a in (reference, image))
    if ref.shape != img.shape:
        raise InputError(f"frames differ in size: {reference.shape} vs {image.shape}")
    warp = np.eye(2, 3, dtype=np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-7)
    try:
        _cc, warp = cv2.findTransformECC(ref, img, warp, cv2.MOTION_AFFINE, criteria, None, 5)
    except cv2.error as err:
        raise InputError(f"cannot register the frames to measure their scale: {err}") from err
    return float(math.sqrt(abs(np.linalg.det(warp[:, :2].astype(np.float64)))))


def _gray_small(image: np.ndarray, max_side: int) -> np.ndarray:
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 3:
        a = a.mean(axis=2)
    factor = max(a.shape) / max_side
    if factor > 1:
        a = cv2.resize(a, None, fx=1 / factor, fy=1 / factor, interpolation=cv2.INTER_AREA)
    return (a - a.mean()) / (a.std() + 1e-12)


@dataclass(frozen=True)
class StepCalibration:
    step_image_distance_um: float  # |dp/dstep|
    sign: int  # +1 if + steps lengthen p, -1 if they shorten it (focus farther)
    rms_residual_um: float
    scales: tuple[float, ...]
    steps: tuple[int, ...]


def fit_step_size(steps, scales, reference_image_distance_mm: float) -> StepCalibration:
    """Least-squares mm/step from scales ``s_i = p_i / p_ref`` at drive positions ``steps``."""
    x = np.asarray(steps, dtype=np.float64)
    s = np.asarray(scales, dtype=np.float64)
    if x.size < 2 or x.size != s.size or np.ptp(x) == 0:
        raise InputError(f"calibration needs >= 2 frames at different focus_step, got {x.tolist()}")
    dp_mm = reference_image_distance_mm * (s - 1.0)  # p_i - p_ref = p_ref (s_i - 1)
    dx = x - x[0]
    slope = float(dx @ dp_mm / (dx @ dx))  # line through the reference frame
    residual = dp_mm - slope * dx
    return StepCalibration(
        step_image_distance_um=abs(slope) * 1e3, sign=1 if slope > 0 else -1,
        rms_residual_um=float(np.sqrt(np.mean(residual**2))) * 1e3,
        scales=tuple(s.tolist()), steps=tuple(int(v) for v in x),
    )


def read_stack_frames(stack_dir: Path) -> tuple[list[int], list[np.ndarray]]:
    """focus_step and pixels of every frame listed in ``stack_dir/stack.toml`` (in step order)."""
    toml = stack_dir / "stack.toml"
    try:
        meta = tomllib.loads(toml.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise InputError(f"{toml}: cannot read the stack description: {err}") from err
    frames = meta.get("frames", [])
    if any("focus_step" not in f for f in frames) or len(frames) < 2:
        raise InputError(f"{toml}: calibration needs >= 2 [[frames]] with focus_step")
    steps, images = [], []
    for frame in sorted(frames, key=lambda f: f["focus_step"]):
        path = stack_dir / frame["file"]
        image = cv2.imread(
            str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
        )
        if image is None:
            raise InputError(f"{path}: cannot read the frame (missing or not an image)")
        steps.append(int(frame["focus_step"]))
        images.append(image)
    return steps, images


def calibrate_stack(stack_dir: Path, focal_length_mm: float, *,
                    reference_focus_distance_mm: float = math.inf) -> StepCalibration:
    """Measure the step size of a captured stack (first frame in step order is the reference)."""
    steps, images = read_stack_frames(stack_dir)
    scales = [estimate_scale(images[0], image) for image in images]
    p_ref = float(image_distance(focal_length_mm, reference_focus_distance_mm))  # Eq. 1
    return fit_step_size(steps, scales, p_ref)
