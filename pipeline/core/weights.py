"""Frame weights that turn a focal stack into a flexible-DOF capture (Sec. 9, Sec. 5-7).

A detector moving at constant speed over ``[p_min, p_max]`` spends equal time
per unit of image distance. A focal stack samples that sweep at its frames'
positions ``p_i``; giving each frame the length of the interval of ``p`` it
stands for (half-way to each neighbour, clipped to the swept range) makes the
weighted average emulate the sweep (Sec. 9).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError


def _positions(image_distances_mm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = np.asarray(image_distances_mm, dtype=np.float64).ravel()
    if p.size == 0:
        raise InputError("image_distances_mm is empty: a stack needs at least one frame")
    if not np.all(np.isfinite(p)):
        raise InputError(f"image_distances_mm must be finite, got {p.tolist()}")
    unique, inverse, counts = np.unique(p, return_inverse=True, return_counts=True)
    return unique, inverse, counts


def constant_speed_weights(image_distances_mm, *, ends: str = "half") -> np.ndarray:
    """Weights (sum 1) that emulate a constant-speed sweep over the frames' range (Sec. 9).

    Parameters
    ----------
    image_distances_mm : array_like, shape (n,)
        Each frame's focus position (image distance, or any coordinate linear in
        it); any order, non-uniform spacing and duplicates allowed.
    ends : {"half", "full"}
        "half": the sweep runs exactly from the first to the last frame, so the end
        frames stand for half a spacing. "full": it runs half a spacing beyond them
        (each frame stands for the interval around it; equal weights for even
        spacing), which gives points focused at the end frames a kernel closer to
        the interior ones (Sec. 4.1 notes invariance is worst at the sweep's ends).

    Returns
    -------
    ndarray, shape (n,)
        ``w_i`` proportional to the length of ``p`` nearer to ``p_i`` than to any
        other frame, within the swept range; frames at the same position share
        their interval equally. A single frame, or all frames at one position,
        get equal weights.
    """
    if ends not in ("half", "full"):
        raise InputError(f"ends must be 'half' or 'full', got {ends!r}")
    unique, inverse, counts = _positions(image_distances_mm)
    if unique.size == 1:
        return np.full(inverse.size, 1.0 / inverse.size)
    midpoints = 0.5 * (unique[1:] + unique[:-1])
    first, last = unique[0], unique[-1]
    if ends == "full":
        first, last = 2 * unique[0] - midpoints[0], 2 * unique[-1] - midpoints[-1]
    lower = np.concatenate(([first], midpoints))
    upper = np.concatenate((midpoints, [last]))
    cell = (upper - lower) / (last - first)
    return cell[inverse] / counts[inverse]


# ----------------------------------------------------------------------------- flexible DOFs
# A detector position p between two frames is emulated by interpolating those
# frames linearly in p ("hat" basis functions on the sorted distinct positions;
# outside the frames' range, the end frame). A sweep over [lo, hi] at constant
# speed then weights frame i by the mean of its hat over [lo, hi]; over the
# whole range that mean is exactly the cell length of constant_speed_weights.


def _hat(x: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """Linear-interpolation weights (len(x), len(knots)) of positions ``x`` (clamped)."""
    x = np.clip(np.asarray(x, dtype=np.float64), knots[0], knots[-1])
    out = np.zeros((x.size, knots.size))
    if knots.size == 1:
        out[:, 0] = 1.0
        return out
    right = np.clip(np.searchsorted(knots, x, side="right"), 1, knots.size - 1)
    left = right - 1
    frac = (x - knots[left]) / (knots[right] - knots[left])
    rows = np.arange(x.size)
    out[rows, left] = 1.0 - frac
    out[rows, right] += frac
    return out


def _interval(knots: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Mean of each hat over ``[lo, hi]`` (its value at ``lo`` when ``lo == hi``).

    Exact: the hats are linear between knots, so the trapezoid rule on the
    interval split at the knots (and at the clamping ends) integrates them exactly.
    """
    if hi <= lo:
        return _hat(np.array([lo]), knots)[0]
    inner = knots[(knots > lo) & (knots < hi)]
    x = np.concatenate(([lo], inner, [hi]))
    values = _hat(x, knots)
    widths = np.diff(x)
    return (widths @ (0.5 * (values[1:] + values[:-1]))) / (hi - lo)


def _outside(knots: np.ndarray, values: np.ndarray, name: str, outside: str) -> None:
    if outside not in ("raise", "clamp"):
        raise InputError(f"outside must be 'raise' or 'clamp', got {outside!r}")
    tolerance = 1e-9 * max(1.0, float(np.abs(knots).max()))
    bad = (values < knots[0] - tolerance) | (values > knots[-1] + tolerance)
    if outside == "raise" and np.any(bad):
        raise InputError(
            f"{name} reaches {values[bad].min():.6g}..{values[bad].max():.6g} mm, outside the "
            f"stack's focus positions [{knots[0]:.6g}, {knots[-1]:.6g}] mm; change the target "
            "or pass outside='clamp' (use the end frames)"
        )


def _spread(cell_weights: np.ndarray, inverse: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Weights on distinct positions -> per frame (duplicates share equally)."""
    return cell_weights[..., inverse] / counts[inverse]


def discontinuous_weights(
    image_distances_mm, ranges_image_mm, fractions, *, outside: str = "raise"
) -> np.ndarray:
    """Frame weights that emulate a detector dwelling on several focus ranges (Sec. 5, 9).

    Parameters
    ----------
    image_distances_mm : array_like, shape (n,)
        Each frame's focus position (image distance); any order, duplicates allowed.
    ranges_image_mm : sequence of (lo, hi)
        Image-distance ranges (mm) to dwell on; ``lo == hi`` is a pause at one
        position. Order within a pair does not matter.
    fractions : sequence of float
        Relative time share of each range (> 0; normalised to sum 1).
    outside : {"raise", "clamp"}
        A range beyond the frames' positions is an error, or uses the end frame.

    Returns
    -------
    ndarray, shape (n,)
        Weights summing to 1: ``sum_j f_j * mean over [lo_j, hi_j] of hat_i(p)``,
        where ``hat_i`` linearly interpolates frames in ``p``. A range is swept at
        constant speed (the same measure as :func:`constant_speed_weights`, which
        this equals for one range spanning the stack); a pause interpolates the
        two frames around it. The transits between ranges (Sec. 5) are not
        emulated: the synthesis jumps instantly.
    """
    knots, inverse, counts = _positions(image_distances_mm)
    ranges = np.asarray(ranges_image_mm, dtype=np.float64)
    if ranges.ndim != 2 or ranges.shape[1] != 2 or ranges.shape[0] == 0:
        raise InputError(
            "ranges_image_mm must be a non-empty sequence of (lo, hi) pairs, "
            f"got {ranges_image_mm!r}"
        )
    if not np.all(np.isfinite(ranges)):
        raise InputError(f"ranges_image_mm must be finite (mm), got {ranges.tolist()}")
    shares = np.asarray(fractions, dtype=np.float64).ravel()
    if shares.size != ranges.shape[0]:
        raise InputError(
            f"fractions must give one share per range: {ranges.shape[0]} ranges, "
            f"{shares.size} fractions"
        )
    if not np.all(np.isfinite(shares)) or np.any(shares <= 0):
        raise InputError(f"fractions must be finite and > 0, got {shares.tolist()}")
    _outside(knots, ranges.ravel(), "ranges_image_mm", outside)
    shares = shares / shares.sum()
    cells = sum(
        share * _interval(knots, float(lo), float(hi))
        for share, (lo, hi) in zip(shares, np.sort(ranges, axis=1))
    )
    return _spread(cells, inverse, counts)


def row_weights(
    image_distances_mm, row_positions_mm, *, window_mm: float = 0.0, outside: str = "raise"
) -> np.ndarray:
    """Per-row frame weights: every image row gets its own detector position (Sec. 6, 7, 9).

    Emulates a rolling-shutter capture whose row ``r`` is exposed at position
    ``p_r`` (a tilted DOF when ``p_r`` is linear in ``r``, non-planar otherwise).

    Parameters
    ----------
    image_distances_mm : array_like, shape (n,)
        Each frame's focus position; any order, duplicates allowed.
    row_positions_mm : array_like, shape (rows,)
        Target detector position ``p_r`` of every row.
    window_mm : float
        0 (default): linear interpolation between the two frames around ``p_r``.
        > 0: a constant-speed sweep through ``[p_r - w/2, p_r + w/2]`` (a row
        exposed while the detector moves), interpolated the same way.
    outside : {"raise", "clamp"}
        Positions beyond the frames' range are an error, or use the end frame.

    Returns
    -------
    ndarray, shape (rows, n)
        Each row sums to 1; its weighted mean frame position is ``p_r`` wherever
        ``[p_r - w/2, p_r + w/2]`` lies inside the frames' range.
    """
    knots, inverse, counts = _positions(image_distances_mm)
    p = np.asarray(row_positions_mm, dtype=np.float64)
    if p.ndim != 1 or p.size == 0 or not np.all(np.isfinite(p)):
        raise InputError(
            f"row_positions_mm must be a non-empty 1-D array of finite mm, got shape {p.shape}"
        )
    if not isinstance(window_mm, (int, float)) or not 0 <= window_mm < np.inf:
        raise InputError(f"window_mm must be a number of mm >= 0, got {window_mm!r}")
    half = 0.5 * window_mm
    _outside(knots, np.concatenate((p - half, p + half)), "row_positions_mm", outside)
    if half == 0:
        cells = _hat(p, knots)
    else:
        cells = np.stack([_interval(knots, x - half, x + half) for x in p])
    return _spread(cells, inverse, counts)


def frame_noise_gain(weights) -> float:
    """How much quieter the weighted average is than one frame: ``sum w / sqrt(sum w^2)``.

    The frames' noise is independent, so the average's noise std is one frame's times
    ``sqrt(sum w^2) / sum w``. A deconvolution that amplifies white noise by at most this
    factor leaves the result about as noisy as one frame (issue 13's noise target).
    """
    w = np.asarray(weights, dtype=np.float64).ravel()
    energy = float(np.sum(w**2))
    if not np.all(np.isfinite(w)) or np.any(w < 0) or energy <= 0:
        raise InputError("weights must be finite, non-negative and not all zero")
    return float(np.sum(w) / np.sqrt(energy))
