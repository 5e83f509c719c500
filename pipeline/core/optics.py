"""Thin-lens geometry of a camera whose detector (or lens) moves: Eqs. 1, 2, 9 and Fig. 2.

All lengths are millimetres; ``math.inf`` is a valid focus distance (the lens
law then gives ``v = f``). Functions accept floats or NumPy arrays.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.core.validate import positive_array
from pipeline.errors import InputError


def _out(arr: np.ndarray):
    return float(arr) if arr.ndim == 0 else arr


def image_distance(focal_length_mm: float, focus_distance_mm):
    """Image distance ``v`` at which a point at depth ``u`` is in focus (Eq. 1).

    ``1/f = 1/u + 1/v``, so ``v = f u / (u - f)``; ``u = inf`` gives ``v = f``.

    Raises
    ------
    InputError
        If ``focus_distance_mm <= focal_length_mm``: such a point forms no real image.
    """
    f = float(positive_array("focal_length_mm", focal_length_mm))
    u = positive_array("focus_distance_mm", focus_distance_mm)
    if np.any(u <= f):
        raise InputError(
            f"focus_distance_mm must exceed the focal length {f} mm (no real image otherwise), "
            f"got {focus_distance_mm!r}"
        )
    with np.errstate(invalid="ignore"):
        v = np.where(np.isinf(u), f, f * u / (u - f))  # Eq. 1
    return _out(v)


def focus_distance(focal_length_mm: float, image_distance_mm):
    """Depth ``u`` in focus when the detector is at ``v`` (Eq. 1); ``v = f`` gives ``inf``."""
    f = float(positive_array("focal_length_mm", focal_length_mm))
    v = positive_array("image_distance_mm", image_distance_mm)
    if np.any(v < f):
        raise InputError(
            f"image_distance_mm must be >= the focal length {f} mm (nothing is in focus closer), "
            f"got {image_distance_mm!r}"
        )
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(v == f, math.inf, f * v / (v - f))  # Eq. 1
    return _out(u)


def blur_diameter_mm(aperture_mm: float, image_distance_mm, detector_distance_mm):
    """Blur-circle diameter ``b = a |v - p| / v`` on the detector (Eq. 2).

    ``image_distance_mm`` is ``v``, where the point would focus; ``detector_distance_mm``
    is the detector's position ``p``.
    """
    a = positive_array("aperture_mm", aperture_mm)
    v = positive_array("image_distance_mm", image_distance_mm)
    p = positive_array("detector_distance_mm", detector_distance_mm)
    return _out(a / v * np.abs(v - p))  # Eq. 2


def sweep_translation(focal_length_mm: float, near_mm: float, far_mm: float) -> float:
    """Detector translation (mm) that sweeps the focal plane from ``far_mm`` to ``near_mm``.

    The third column of Fig. 2: ``v(near) - v(far)``; ``far_mm`` may be ``math.inf``.
    """
    if not near_mm < far_mm:
        raise InputError(f"near_mm must be < far_mm, got near={near_mm!r}, far={far_mm!r}")
    v_near = image_distance(focal_length_mm, near_mm)
    v_far = image_distance(focal_length_mm, far_mm)
    return float(v_near - v_far)


def image_position_change_px(
    focal_length_mm: float,
    near_mm: float,
    far_mm: float,
    *,
    width_px: int,
    height_px: int,
) -> float:
    """Largest shift of a scene point's image caused by the sweep (Fig. 2, fourth column).

    A chief ray through the lens centre lands at radius ``r p / p_far`` when the
    detector moves from ``p_far = v(far)`` to ``p``, so a point imaged at the sensor
    corner (half-diagonal ``r``) moves by ``r (v(near) - v(far)) / v(far)``.

    Notes
    -----
    The paper's fourth column (e.g. 3.6 px for 12.5 mm, 1 m - inf, but 4.5 px for
    9 mm with half the translation) is not reproduced by this or any single
    geometric model we tried (corner, edge, or row centre); we implement the
    geometry above and test it against ray tracing, not against that column.
    """
    translation = sweep_translation(focal_length_mm, near_mm, far_mm)
    p_far = image_distance(focal_length_mm, far_mm)
    half_diagonal_px = 0.5 * math.hypot(width_px, height_px)
    return half_diagonal_px * translation / p_far


def depth_of_field(
    focal_length_mm: float, f_number: float, focus_distance_mm: float, coc_mm: float
) -> tuple[float, float]:
    """Near and far limits of a normal camera's DOF for a circle of confusion ``c``.

    Exact from Eq. 2 rather than the usual hyperfocal approximation: with the
    detector at ``p = v(focus)``, a depth is acceptably sharp when
    ``a |v - p| / v <= c``, i.e. ``v`` in ``[p a / (a + c), p a / (a - c)]``.
    The far limit is ``inf`` when ``p a / (a + c) <= f``; the near limit is the lens
    (``f``) when ``c >= a``.
    """
    positive_array("f_number", f_number)
    positive_array("coc_mm", coc_mm)
    a = focal_length_mm / f_number
    p = image_distance(focal_length_mm, focus_distance_mm)
    v_far = p * a / (a + coc_mm)
    far = math.inf if v_far <= focal_length_mm else focus_distance(focal_length_mm, v_far)
    near = focal_length_mm if coc_mm >= a else focus_distance(focal_length_mm, p * a / (a - coc_mm))
    return float(near), float(far)


def detector_tilt_deg(speed_mm_s: float, readout_s: float, sensor_height_mm: float) -> float:
    """Tilt ``theta`` of the detector a rolling shutter emulates, ``atan(s T / H)`` (Eq. 9).

    ``readout_s`` is ``T``, the delay between the first and last row; the sign
    follows ``speed_mm_s``.
    """
    positive_array("readout_s", readout_s)
    positive_array("sensor_height_mm", sensor_height_mm)
    if not math.isfinite(speed_mm_s):
        raise InputError(f"speed_mm_s must be finite, got {speed_mm_s!r}")
    return math.degrees(math.atan(speed_mm_s * readout_s / sensor_height_mm))  # Eq. 9


def focal_plane_tilt_deg(
    focal_length_mm: float,
    start_image_distance_mm: float,
    sensor_height_mm: float,
    detector_tilt: float,
) -> float:
    """Scheimpflug tilt ``phi`` of the focal plane for a detector tilt ``theta`` (Eq. 9).

    ``phi = atan(2 f tan(theta) / (2 p(0) + H tan(theta) - 2 f))`` with ``p(0)`` the
    detector position when the first row is exposed. Verified against tracing the
    conjugates of the first and last rows through the thin lens (tests).
    """
    f = focal_length_mm
    tan_theta = math.tan(math.radians(detector_tilt))
    denominator = 2 * start_image_distance_mm + sensor_height_mm * tan_theta - 2 * f
    if denominator <= 0:
        raise InputError(
            "the detector rows reach the focal length (no real focal plane): "
            f"p(0)={start_image_distance_mm} mm, f={f} mm, tilt={detector_tilt} deg"
        )
    return math.degrees(math.atan(2 * f * tan_theta / denominator))  # Eq. 9


def speed_for_focal_plane_tilt(
    focal_length_mm: float,
    start_image_distance_mm: float,
    sensor_height_mm: float,
    readout_s: float,
    plane_tilt_deg: float,
) -> float:
    """Detector speed (mm/s) that tilts the focal plane by ``phi`` (Eq. 9 inverted).

    ``tan(theta) = tan(phi) (2 p(0) - 2 f) / (2 f - H tan(phi))`` and ``s = H tan(theta) / T``.
    """
    positive_array("readout_s", readout_s)
    f, p0, h = focal_length_mm, start_image_distance_mm, sensor_height_mm
    if p0 <= f:
        raise InputError(f"start_image_distance_mm must exceed f={f} mm, got {p0!r}")
    if not -90 < plane_tilt_deg < 90:
        raise InputError(f"plane_tilt_deg must be in (-90, 90), got {plane_tilt_deg!r}")
    tan_phi = math.tan(math.radians(plane_tilt_deg))
    denominator = 2 * f - h * tan_phi
    if denominator <= 0:
        raise InputError(
            f"a focal-plane tilt of {plane_tilt_deg} deg is unreachable with f={f} mm and a "
            f"{h:.3f} mm detector (needs tan(phi) < 2f/H = {2 * f / h:.3f})"
        )
    tan_theta = tan_phi * (2 * p0 - 2 * f) / denominator
    return h * tan_theta / readout_s
