"""Detector (or lens) motion profiles p(t) during an exposure (Sec. 3-8).

A :class:`Profile` is piecewise linear: image distance ``p`` (mm, the
lens-to-detector distance) at strictly increasing times (s). Constant speed
(Sec. 4), pauses (Sec. 5's discontinuous DOF), several segments and reversals
(Sec. 4.2's alternating EDOF video) are all piecewise linear. Moving the lens
instead of the detector gives the same geometry (Sec. 8).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.errors import InputError


@dataclass(frozen=True, eq=False)
class Profile:
    """Piecewise-linear detector position p(t).

    Parameters
    ----------
    times_s : sequence of float
        Strictly increasing knot times; the exposure is ``[times_s[0], times_s[-1]]``.
    image_distances_mm : sequence of float
        Detector position p at each knot (mm from the lens), all > 0.
    """

    times_s: np.ndarray
    image_distances_mm: np.ndarray

    def __init__(self, times_s: Sequence[float], image_distances_mm: Sequence[float]) -> None:
        times = np.asarray(times_s, dtype=np.float64).ravel()
        positions = np.asarray(image_distances_mm, dtype=np.float64).ravel()
        if times.size < 2 or times.size != positions.size:
            raise InputError(
                "Profile needs at least two knots and as many times_s as image_distances_mm, "
                f"got {times.size} times and {positions.size} positions"
            )
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(positions))):
            raise InputError("Profile times_s and image_distances_mm must be finite (no NaN/inf)")
        if np.any(np.diff(times) <= 0):
            raise InputError(f"Profile times_s must be strictly increasing, got {times.tolist()}")
        if np.any(positions <= 0):
            raise InputError(
                "Profile image_distances_mm must be > 0 (mm from the lens), "
                f"got {positions.tolist()}"
            )
        times.setflags(write=False)
        positions.setflags(write=False)
        object.__setattr__(self, "times_s", times)
        object.__setattr__(self, "image_distances_mm", positions)

    @property
    def exposure_s(self) -> float:
        """Total integration time ``T`` (Eq. 5)."""
        return float(self.times_s[-1] - self.times_s[0])

    @property
    def start_mm(self) -> float:
        return float(self.image_distances_mm[0])

    @property
    def end_mm(self) -> float:
        return float(self.image_distances_mm[-1])

    @property
    def range_mm(self) -> tuple[float, float]:
        """Smallest and largest detector position reached."""
        return float(self.image_distances_mm.min()), float(self.image_distances_mm.max())

    @property
    def max_speed_mm_s(self) -> float:
        return float(np.max(np.abs(np.diff(self.image_distances_mm) / np.diff(self.times_s))))

    def position(self, t_s: float | np.ndarray) -> np.ndarray:
        """p(t) by linear interpolation (clamped outside the exposure)."""
        return np.interp(t_s, self.times_s, self.image_distances_mm)

    def window(self, start_s: float, end_s: float) -> Profile:
        """The part of the motion between two times (one rolling-shutter row's exposure)."""
        t0, t1 = self.times_s[0], self.times_s[-1]
        if not (t0 <= start_s < end_s <= t1 + 1e-12):
            raise InputError(
                f"window [{start_s}, {end_s}] s is not inside the exposure [{t0}, {t1}] s"
            )
        inner = self.times_s[(self.times_s > start_s) & (self.times_s < end_s)]
        times = np.concatenate(([start_s], inner, [min(end_s, t1)]))
        return Profile(times, self.position(times))

    def shifted(self, delay_s: float) -> Profile:
        """The same motion starting ``delay_s`` later."""
        return Profile(self.times_s + delay_s, self.image_distances_mm)

    def segments(self) -> list[tuple[float, float, float]]:
        """(duration_s, p_start_mm, p_end_mm) of each linear segment."""
        durations = np.diff(self.times_s)
        p = self.image_distances_mm
        return [(float(d), float(a), float(b)) for d, a, b in zip(durations, p[:-1], p[1:])]

    def __repr__(self) -> str:
        return (
            f"Profile(times_s={self.times_s.tolist()}, "
            f"image_distances_mm={self.image_distances_mm.tolist()})"
        )


def constant_speed(start_image_distance_mm: float, speed_mm_s: float, exposure_s: float) -> Profile:
    """p(t) = p(0) + s t for ``0 <= t <= T`` (Sec. 4.1); ``speed_mm_s`` may be 0 or negative."""
    for name, value in (
        ("start_image_distance_mm", start_image_distance_mm),
        ("speed_mm_s", speed_mm_s),
        ("exposure_s", exposure_s),
    ):
        if not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"{name} must be a finite number, got {value!r}")
    if exposure_s <= 0:
        raise InputError(f"exposure_s must be > 0, got {exposure_s!r}")
    end = start_image_distance_mm + speed_mm_s * exposure_s
    return Profile([0.0, exposure_s], [start_image_distance_mm, end])
