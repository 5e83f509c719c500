"""Detector (or lens) motion profiles p(t) during an exposure (Sec. 3-8).

A :class:`Profile` is piecewise linear: image distance ``p`` (mm, the
lens-to-detector distance) at strictly increasing times (s). Constant speed
(Sec. 4), pauses (Sec. 5's discontinuous DOF), several segments and reversals
(Sec. 4.2's alternating EDOF video) are all piecewise linear. Moving the lens
instead of the detector gives the same geometry (Sec. 8).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pipeline.core import optics, validate
from pipeline.core.lens import Lens
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
        start, end = max(float(start_s), float(t0)), min(float(end_s), float(t1))
        inner = self.times_s[(self.times_s > start) & (self.times_s < end)]
        times = np.concatenate(([start], inner, [end]))
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
    validate.finite("start_image_distance_mm", start_image_distance_mm)
    validate.finite("speed_mm_s", speed_mm_s)
    validate.positive("exposure_s", exposure_s)
    end = start_image_distance_mm + speed_mm_s * exposure_s
    return Profile([0.0, exposure_s], [start_image_distance_mm, end])


# ----------------------------------------------------------------------------- planning (Sec. 4-7)
def check_actuator(lens: Lens, profile: Profile, *, what: str = "the motion") -> None:
    """Raise :class:`InputError` if ``profile`` exceeds the lens's actuator limits.

    Checks the fastest segment against ``max_speed_mm_s`` and the positions
    reached against ``travel_mm`` (the stroke), and that every position is
    behind the focal length (``p >= f``: nothing focuses closer).
    """
    speed = profile.max_speed_mm_s
    if speed > lens.max_speed_mm_s * (1 + 1e-9):
        raise InputError(
            f"{what} needs {speed:.4g} mm/s but the actuator of {lens.name!r} reaches "
            f"max_speed_mm_s={lens.max_speed_mm_s:g} mm/s; lengthen exposure_s or narrow the range"
        )
    low, high = profile.range_mm
    if high - low > lens.travel_mm * (1 + 1e-9):
        raise InputError(
            f"{what} moves the detector over {high - low:.4g} mm but {lens.name!r} has "
            f"travel_mm={lens.travel_mm:g} mm; narrow the depth range"
        )
    if low < lens.focal_length_mm * (1 - 1e-12):
        raise InputError(
            f"{what} puts the detector at {low:.5g} mm, closer than the focal length "
            f"{lens.focal_length_mm:g} mm (beyond infinity focus); change the target"
        )


def _check_depth_range(near_mm: float, far_mm: float, lens: Lens, name: str) -> None:
    for label, value in (("near", near_mm), ("far", far_mm)):
        if not isinstance(value, (int, float)) or math.isnan(value):
            raise InputError(f"{name}: {label} must be a number of mm, got {value!r}")
    if not lens.focal_length_mm < near_mm <= far_mm:
        raise InputError(
            f"{name} must satisfy focal length {lens.focal_length_mm:g} mm < near <= far "
            f"(far may be inf), got near={near_mm!r}, far={far_mm!r}"
        )


def _check_positive_time(name: str, value: float) -> None:
    validate.positive(name, value)


def plan_extended_dof(lens: Lens, near_mm: float, far_mm: float, exposure_s: float) -> Profile:
    """Constant-speed sweep that moves the focal plane from ``far_mm`` to ``near_mm`` (Sec. 4).

    ``p(t) = v(far) + s t`` with ``s = (v(near) - v(far)) / T`` (Eq. 1 for ``v``).

    Parameters
    ----------
    lens : Lens
        Focal length and actuator limits (``max_speed_mm_s``, ``travel_mm``).
    near_mm, far_mm : float
        Depth range to keep in focus; ``far_mm`` may be ``math.inf``.
    exposure_s : float
        Integration time ``T``.

    Raises
    ------
    InputError
        If the range is empty or invalid, or the sweep needs more speed or travel
        than the actuator has (the message gives the shortest feasible exposure).
    """
    _check_depth_range(near_mm, far_mm, lens, "plan_extended_dof(near_mm, far_mm)")
    _check_positive_time("exposure_s", exposure_s)
    if near_mm == far_mm:
        raise InputError(f"near_mm and far_mm are equal ({near_mm} mm): the range is empty")
    start = optics.image_distance(lens.focal_length_mm, far_mm)
    end = optics.image_distance(lens.focal_length_mm, near_mm)
    speed = (end - start) / exposure_s
    if speed > lens.max_speed_mm_s:
        raise InputError(
            f"sweeping {near_mm:g}-{far_mm:g} mm in exposure_s={exposure_s:g} s needs "
            f"{speed:.4g} mm/s, more than max_speed_mm_s={lens.max_speed_mm_s:g} of "
            f"{lens.name!r}; use exposure_s >= {(end - start) / lens.max_speed_mm_s:.4g} s"
        )
    profile = constant_speed(start, speed, exposure_s)
    check_actuator(lens, profile, what=f"the sweep {near_mm:g}-{far_mm:g} mm")
    return profile


def plan_discontinuous_dof(
    lens: Lens,
    ranges: Sequence[tuple[float, float]],
    fractions: Sequence[float],
    exposure_s: float,
    *,
    transit: str | float = "max-speed",
) -> Profile:
    """Focus on several depth ranges in one exposure (Sec. 5, Fig. 10).

    The ranges are visited in order of image distance (far to near); each is
    swept at constant speed (``near < far``) or held still (``near == far``, a
    pause) for its share of the dwell time; between ranges the detector moves
    at the transit speed.

    Parameters
    ----------
    lens : Lens
    ranges : sequence of (near_mm, far_mm)
        Depth ranges to focus on; non-overlapping; ``far_mm`` may be ``inf``.
    fractions : sequence of float
        Relative time share of each range (> 0; normalised to sum 1) of the time
        left after the transits.
    exposure_s : float
        Total integration time ``T``, transits included.
    transit : "max-speed" or float
        Speed (mm/s) of the moves between ranges; "max-speed" is the actuator's
        ``max_speed_mm_s`` (the shortest transits, so intermediate depths get the
        least exposure, Sec. 5).

    Raises
    ------
    InputError
        Invalid or overlapping ranges, fractions that do not match, transits
        longer than the exposure, or a sweep faster than the actuator.
    """
    ranges = list(ranges)
    fractions = list(fractions)
    _check_positive_time("exposure_s", exposure_s)
    if not ranges:
        raise InputError("ranges is empty: give at least one (near_mm, far_mm) range")
    if len(fractions) != len(ranges):
        raise InputError(
            f"fractions must give one share per range: {len(ranges)} ranges, "
            f"{len(fractions)} fractions"
        )
    shares = np.asarray(fractions, dtype=np.float64)
    if not np.all(np.isfinite(shares)) or np.any(shares <= 0):
        raise InputError(f"fractions must be finite and > 0, got {fractions!r}")
    shares = shares / shares.sum()
    f = lens.focal_length_mm
    spans = []
    for i, rng in enumerate(ranges):
        if len(rng) != 2:
            raise InputError(f"ranges[{i}] must be (near_mm, far_mm), got {rng!r}")
        _check_depth_range(rng[0], rng[1], lens, f"ranges[{i}]")
        spans.append((optics.image_distance(f, rng[1]), optics.image_distance(f, rng[0])))
    order = np.argsort([lo for lo, _ in spans], kind="stable")
    spans = [spans[i] for i in order]
    shares = shares[order]
    gaps = [lo_b - hi_a for (_, hi_a), (lo_b, _) in itertools.pairwise(spans)]
    for gap, i, j in zip(gaps, order, order[1:]):
        if gap <= 0:
            raise InputError(
                f"ranges[{i}] {ranges[i]} and ranges[{j}] {ranges[j]} overlap or touch; "
                "merge them into one range"
            )
    if transit == "max-speed":
        transit_speed = lens.max_speed_mm_s
        if not math.isfinite(transit_speed):
            raise InputError(
                f"transit='max-speed' needs a finite max_speed_mm_s in lens {lens.name!r}; "
                "set it in the profile or pass transit=<speed in mm/s>"
            )
    elif isinstance(transit, (int, float)) and math.isfinite(transit) and transit > 0:
        transit_speed = float(transit)
    else:
        raise InputError(f"transit must be 'max-speed' or a speed in mm/s > 0, got {transit!r}")
    transit_s = sum(gaps) / transit_speed
    dwell_s = exposure_s - transit_s
    if dwell_s <= 0:
        raise InputError(
            f"moving between the ranges takes {transit_s:.4g} s at {transit_speed:g} mm/s, "
            f"not less than exposure_s={exposure_s:g} s; lengthen the exposure"
        )
    times, positions = [0.0], [spans[0][0]]
    for k, ((lo, hi), share) in enumerate(zip(spans, shares)):
        if k:
            times.append(times[-1] + gaps[k - 1] / transit_speed)
            positions.append(lo)
        times.append(times[-1] + share * dwell_s)
        positions.append(hi)
    profile = Profile(times, positions)
    check_actuator(lens, profile, what="the discontinuous-DOF motion")
    return profile


def _check_rolling(lens: Lens, what: str) -> None:
    if lens.shutter != "rolling":
        raise InputError(
            f"{what} needs a rolling shutter (Sec. 6), but lens {lens.name!r} has "
            f"shutter={lens.shutter!r}; use a rolling-shutter profile"
        )


def row_offsets_mm(n_rows: int, sensor_height_mm: float) -> np.ndarray:
    """Height of every row's centre below the optical axis (mm), image rows top to bottom.

    The rows tile ``sensor_height_mm``; the optical axis is at the centre.
    """
    if isinstance(n_rows, bool) or not isinstance(n_rows, (int, np.integer)) or n_rows < 1:
        raise InputError(f"n_rows must be a positive integer, got {n_rows!r}")
    pitch = sensor_height_mm / n_rows
    return (np.arange(n_rows) - 0.5 * (n_rows - 1)) * pitch


def tilted_row_image_distances(
    focal_length_mm: float, plane_tilt_deg: float, through_mm: float, row_offsets: np.ndarray
) -> np.ndarray:
    """Detector position per row that focuses every row on one tilted scene plane (Sec. 6).

    The plane passes through depth ``U = through_mm`` on the optical axis and is
    tilted by ``phi`` about the horizontal axis: ``u = U + Y tan(phi)`` at scene
    height ``Y`` (up), so ``phi > 0`` recedes towards the top of the image (a
    table top, Fig. 11). A row at ``y`` below the axis sees, along its chief ray,
    ``Y = -y u / p = -y (u - f) / f`` (Eq. 1), which meets the plane at
    ``u = (U + y tan(phi)) / (1 + y tan(phi) / f)``; its image distance is then
    ``p(y) = v(U) + y tan(phi) f / (U - f)``, linear in ``y``: a detector tilted by
    ``tan(theta) = tan(phi) (v(U) - f) / f``, Eq. 9's Scheimpflug relation.

    Returns
    -------
    ndarray
        ``p`` (mm) per row; values ``<= f`` mean the row's chief ray meets the
        plane at or beyond infinity (callers validate).
    """
    f = float(focal_length_mm)
    if not -90 < plane_tilt_deg < 90:
        raise InputError(f"plane_tilt_deg must be in (-90, 90), got {plane_tilt_deg!r}")
    if not through_mm > f or not math.isfinite(through_mm):
        raise InputError(
            f"through_mm must be a finite depth beyond the focal length {f:g} mm, "
            f"got {through_mm!r}"
        )
    y = np.asarray(row_offsets, dtype=np.float64)
    slope = math.tan(math.radians(plane_tilt_deg)) * f / (through_mm - f)
    return optics.image_distance(f, through_mm) + y * slope


def plan_tilted_dof(
    lens: Lens, plane_tilt_deg: float, through_mm: float, *, exposure_s: float = 0.0
) -> Profile:
    """Constant-speed motion of a rolling-shutter detector that tilts the DOF (Sec. 6, Eq. 9).

    Rows are read top to bottom, row ``r`` starting its exposure at
    ``r * line_time``; the middle of the read-out focuses at ``through_mm``, and
    the speed comes from Eq. 9 (:func:`pipeline.core.optics.speed_for_focal_plane_tilt`)
    with ``H`` the span of the row centres and ``T`` the lens's read-out time.

    Parameters
    ----------
    lens : Lens
        Rolling-shutter profile (``line_time_us``) with actuator limits.
    plane_tilt_deg : float
        Focal-plane tilt ``phi`` (see :func:`tilted_row_image_distances` for the sign).
    through_mm : float
        Depth of the focal plane on the optical axis (image centre).
    exposure_s : float
        Each row's exposure; the motion is extended by it so that every row's
        mean position is its target (``p(r * line_time + exposure_s / 2)``).

    Raises
    ------
    InputError
        Global shutter, a tilt beyond Eq. 9's limit ``tan(phi) < 2 f / H``, or
        more speed or travel than the actuator has (the message gives the
        largest feasible tilt).
    """
    _check_rolling(lens, "a tilted DOF")
    if not isinstance(exposure_s, (int, float)) or not 0 <= exposure_s < math.inf:
        raise InputError(f"exposure_s must be a number of seconds >= 0, got {exposure_s!r}")
    f = lens.focal_length_mm
    readout = lens.readout_time_s
    height = (lens.height_px - 1) * lens.pixel_pitch_mm  # span of the row centres
    v_centre = tilted_row_image_distances(f, plane_tilt_deg, through_mm, np.zeros(1))[0]
    tan_theta = math.tan(math.radians(plane_tilt_deg)) * (v_centre - f) / f
    p_first = v_centre - 0.5 * height * tan_theta
    try:
        speed = optics.speed_for_focal_plane_tilt(f, p_first, height, readout, plane_tilt_deg)
    except InputError as err:
        raise InputError(f"plane_tilt_deg={plane_tilt_deg!r} is infeasible: {err}") from err
    if abs(speed) > lens.max_speed_mm_s:
        theta_max = math.atan(lens.max_speed_mm_s * readout / height)
        phi_max = math.degrees(math.atan(f * math.tan(theta_max) / (v_centre - f)))
        raise InputError(
            f"plane_tilt_deg={plane_tilt_deg:g} through {through_mm:g} mm needs "
            f"{abs(speed):.4g} mm/s over the {readout * 1e3:.4g} ms read-out, more than "
            f"max_speed_mm_s={lens.max_speed_mm_s:g} of {lens.name!r}; the largest tilt "
            f"there is +-{phi_max:.3g} deg"
        )
    lead = 0.5 * exposure_s
    start = p_first - speed * lead
    duration = readout + exposure_s
    if start <= 0:
        raise InputError(
            f"plane_tilt_deg={plane_tilt_deg:g} through {through_mm:g} mm puts the detector "
            "behind the lens; reduce the tilt or exposure_s"
        )
    profile = constant_speed(start, speed, duration)
    check_actuator(lens, profile, what=f"a {plane_tilt_deg:g} deg tilted DOF")
    return profile


def row_image_distances(
    focal_length_mm: float, row_depths_mm, n_rows: int
) -> tuple[np.ndarray, np.ndarray]:
    """Detector position per row from in-focus depths at some rows (Sec. 7).

    Parameters
    ----------
    focal_length_mm : float
    row_depths_mm : array_like
        Either ``(n_rows,)`` depths, one per row, or ``(k, 2)`` knots
        ``(row, depth_mm)`` with distinct integer rows in ``[0, n_rows)``.
    n_rows : int

    Returns
    -------
    knot_rows, knot_positions : ndarray
        Sorted knot rows and their image distances ``v(depth)`` (Eq. 1).
        Between knots ``p`` is linear in the row (so in time for a rolling
        shutter); before the first and after the last knot it is constant.
    """
    data = np.asarray(row_depths_mm, dtype=np.float64)
    if data.ndim == 1:
        if data.size != n_rows:
            raise InputError(
                f"row_depths_mm has {data.size} depths but the detector has {n_rows} rows; "
                "give one depth per row or (row, depth_mm) pairs"
            )
        rows = np.arange(n_rows, dtype=np.float64)
        depths = data
    elif data.ndim == 2 and data.shape[1] == 2 and data.shape[0] >= 1:
        rows, depths = data[:, 0], data[:, 1]
        if (
            not np.all(np.isfinite(rows))
            or np.any(rows != np.round(rows))
            or np.any(rows < 0)
            or np.any(rows >= n_rows)
        ):
            raise InputError(
                f"row_depths_mm rows must be integers in [0, {n_rows}), got {rows.tolist()}"
            )
        if np.unique(rows).size != rows.size:
            raise InputError(f"row_depths_mm lists a row twice: {rows.tolist()}")
    else:
        raise InputError(
            "row_depths_mm must be (n_rows,) depths or (k, 2) (row, depth_mm) pairs, "
            f"got shape {data.shape}"
        )
    if np.any(np.isnan(depths)) or np.any(depths <= focal_length_mm):
        raise InputError(
            f"row depths must exceed the focal length {focal_length_mm:g} mm (inf allowed), "
            f"got {depths.tolist()}"
        )
    order = np.argsort(rows)
    return rows[order], np.asarray(optics.image_distance(focal_length_mm, depths[order]))


def plan_nonplanar_dof(lens: Lens, row_depths_mm, *, exposure_s: float = 0.0) -> Profile:
    """Piecewise-linear motion of a rolling-shutter detector for a per-row depth (Sec. 7).

    Row ``r`` starts its exposure at ``t = r * line_time``; the detector is at
    ``v(depth_r)`` then (plus ``exposure_s / 2``, so the row's mean position is
    its target), moving linearly between the given rows and holding still
    before the first and after the last.

    Parameters
    ----------
    lens : Lens
        Rolling-shutter profile with actuator limits.
    row_depths_mm : array_like
        ``(height_px,)`` depths or ``(k, 2)`` ``(row, depth_mm)`` knots
        (see :func:`row_image_distances`).
    exposure_s : float
        Each row's exposure (>= 0).

    Raises
    ------
    InputError
        Global shutter, invalid rows/depths, or a speed between two rows above
        ``max_speed_mm_s`` (naming the rows) or travel above ``travel_mm``.
    """
    _check_rolling(lens, "a non-planar DOF")
    if not isinstance(exposure_s, (int, float)) or not 0 <= exposure_s < math.inf:
        raise InputError(f"exposure_s must be a number of seconds >= 0, got {exposure_s!r}")
    rows, positions = row_image_distances(lens.focal_length_mm, row_depths_mm, lens.height_px)
    line_time = lens.line_time_us * 1e-6
    times = rows * line_time + 0.5 * exposure_s
    if rows.size > 1:
        speeds = np.abs(np.diff(positions) / np.diff(times))
        worst = int(np.argmax(speeds))
        if speeds[worst] > lens.max_speed_mm_s * (1 + 1e-9):
            raise InputError(
                f"rows {rows[worst]:.0f} -> {rows[worst + 1]:.0f} need "
                f"{speeds[worst]:.4g} mm/s (focus {positions[worst]:.5g} -> "
                f"{positions[worst + 1]:.5g} mm in {np.diff(times)[worst] * 1e3:.4g} ms), more "
                f"than max_speed_mm_s={lens.max_speed_mm_s:g} of {lens.name!r}; "
                "smooth the depth profile"
            )
    end = (lens.height_px - 1) * line_time + exposure_s
    if times[0] > 0:
        times = np.concatenate(([0.0], times))
        positions = np.concatenate(([positions[0]], positions))
    if times[-1] < end:
        times = np.concatenate((times, [end]))
        positions = np.concatenate((positions, [positions[-1]]))
    profile = Profile(times, positions)
    check_actuator(lens, profile, what="the non-planar DOF motion")
    return profile
