"""Flexible DOFs synthesised from a focal stack (Secs. 5-7, through Sec. 9).

A discontinuous DOF (depth ranges in focus, Sec. 5), a tilted focal plane (Sec. 6,
Eq. 9) or a per-row focal surface (Sec. 7) is a weighted sum of the aligned frames
of a focal stack (:mod:`pipeline.core.weights`): an optical-style result, without
deconvolution. It runs the main job's path (:mod:`pipeline.jobs.stack`): the same
loading, alignment, streaming accumulation, progress and atomic image + sidecar.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.core import motion, optics, weights
from pipeline.core.lens import Lens
from pipeline.errors import InputError
from pipeline.jobs.options import Progress, StackOptions, StackResult, _no_progress
from pipeline.jobs.result import check_output, write_result
from pipeline.jobs.stack import (
    accumulate,
    align_stack,
    load,
    normalise_exposure,
    stack_sidecar,
)

log = logging.getLogger(__name__)

TARGETS = ("in-focus", "tilt", "rows")


@dataclasses.dataclass(frozen=True)
class DofTarget:
    """What should be in focus: exactly one of the three kinds.

    Parameters
    ----------
    in_focus : sequence of (near_mm, far_mm)
        Depth ranges in focus (``far`` may be ``inf``; ``near == far`` pauses at one
        depth): a discontinuous DOF (Sec. 5).
    fractions : sequence of float, optional
        Time share of each range (default: equal shares).
    tilt_deg, at_mm : float, optional
        A focal plane tilted about the horizontal axis by ``tilt_deg``, at depth
        ``at_mm`` at the image centre (Sec. 6, Eq. 9).
    rows_csv : Path, optional
        A CSV of (row, depth_mm) knots: a non-planar DOF (Sec. 7).
    """

    in_focus: tuple[tuple[float, float], ...] = ()
    fractions: tuple[float, ...] | None = None
    tilt_deg: float | None = None
    at_mm: float | None = None
    rows_csv: Path | None = None

    def __post_init__(self) -> None:
        given = [
            name
            for name, on in (
                ("in-focus", bool(self.in_focus)),
                ("tilt", self.tilt_deg is not None or self.at_mm is not None),
                ("rows", self.rows_csv is not None),
            )
            if on
        ]
        if len(given) != 1:
            raise InputError(
                "give exactly one DOF target: --in-focus NEAR:FAR, --tilt-deg A --at-mm U, or "
                f"--rows FILE.csv (got {', '.join(given) or 'none'})"
            )
        if given[0] == "tilt" and (self.tilt_deg is None or self.at_mm is None):
            raise InputError("a tilted DOF needs both --tilt-deg and --at-mm")
        if self.fractions and given[0] != "in-focus":
            raise InputError("--fraction only applies to --in-focus ranges")
        if self.fractions and len(self.fractions) != len(self.in_focus):
            raise InputError(
                f"--fraction given {len(self.fractions)} times for {len(self.in_focus)} "
                "--in-focus ranges; give one per range or none (equal shares)"
            )
        for near, far in self.in_focus:
            if math.isnan(near) or math.isnan(far) or not 0 < near <= far:
                raise InputError(f"--in-focus {near}:{far}: need 0 < NEAR <= FAR (mm)")

    @property
    def kind(self) -> str:
        """``"in-focus"``, ``"tilt"`` or ``"rows"``."""
        if self.in_focus:
            return "in-focus"
        return "tilt" if self.tilt_deg is not None else "rows"


def parse_range(text: str) -> tuple[float, float]:
    """``"NEAR:FAR"`` (mm; ``inf`` allowed) -> (near, far); :class:`DofTarget` checks them."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError(text)
        near, far = float(parts[0]), float(parts[1])
    except ValueError as err:
        raise InputError(f"--in-focus {text!r}: expected NEAR:FAR in mm, e.g. 450:600") from err
    return near, far


def read_rows_csv(path: Path) -> np.ndarray:
    """(row, depth_mm) pairs from a CSV file; a non-numeric first line is a header."""
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            lines = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    except OSError as err:
        raise InputError(f"--rows {path}: cannot read it ({err})") from err
    pairs = []
    for k, line in enumerate(lines):
        try:
            if len(line) != 2:
                raise ValueError(line)
            pairs.append((float(line[0]), float(line[1])))
        except ValueError as err:
            if k == 0:
                continue  # header
            raise InputError(f"--rows {path}: line {k + 1} {line!r} is not 'row,depth_mm'") from err
    if not pairs:
        raise InputError(f"--rows {path}: no (row, depth_mm) lines")
    return np.array(pairs)


# An --in-focus end this close (relative, in depth) beyond the stack's end frame is taken
# as that frame: e.g. 2110 for a stack whose nearest frame is at 2110.4 mm.
RANGE_TOLERANCE = 0.01


def _within_stack(depth_mm: float, stack_near: float, stack_far: float) -> float | None:
    """``depth_mm`` clamped to [stack_near, stack_far] within :data:`RANGE_TOLERANCE`;
    ``None`` when it is farther outside."""
    if stack_near <= depth_mm <= stack_far:
        return depth_mm
    if stack_near * (1 - RANGE_TOLERANCE) <= depth_mm < stack_near:
        return stack_near
    if stack_far < depth_mm <= stack_far * (1 + RANGE_TOLERANCE):
        return stack_far
    return None


def frame_weights(target: DofTarget, lens: Lens, positions: np.ndarray, rows: int) -> np.ndarray:
    """(frames,) weights for a discontinuous DOF, (rows, frames) for a tilted or non-planar one.

    Depth ranges become image-distance ranges by the lens law (Eq. 1); a range end within
    1% beyond the stack's end is clamped to it, one farther out is an error. Rows that ask
    for focus beyond the stack use its nearest end frame (a warning says how many).
    """
    f = lens.focal_length_mm
    if target.kind == "in-focus":
        fractions = list(target.fractions or [1.0] * len(target.in_focus))
        stack_near = float(optics.focus_distance(f, float(positions.max())))
        stack_far = float(optics.focus_distance(f, float(positions.min())))
        image_ranges = []
        for near, far in target.in_focus:
            near_in, far_in = (_within_stack(d, stack_near, stack_far) for d in (near, far))
            if near_in is None or far_in is None:
                raise InputError(
                    f"--in-focus {near:g}:{far:g}: outside the stack's focus range "
                    f"{stack_near:.1f}:{stack_far:.1f} mm (its nearest and farthest frames); "
                    "give ranges within it"
                )
            if (near_in, far_in) != (near, far):
                log.info(
                    "--in-focus %g:%g: clamped to %.1f:%.1f mm (the stack's end frames)",
                    near, far, near_in, far_in,
                )
            image_ranges.append(
                (float(optics.image_distance(f, far_in)), float(optics.image_distance(f, near_in)))
            )
        # every range is within the stack now (up to rounding of the lens law)
        return weights.discontinuous_weights(positions, image_ranges, fractions, outside="clamp")
    if target.kind == "tilt":
        offsets = motion.row_offsets_mm(rows, lens.sensor_height_mm)
        p_rows = motion.tilted_row_image_distances(f, target.tilt_deg, target.at_mm, offsets)
    else:
        knot_rows, knot_p = motion.row_image_distances(f, read_rows_csv(target.rows_csv), rows)
        p_rows = np.interp(np.arange(rows), knot_rows, knot_p)
    outside = (p_rows < positions.min()) | (p_rows > positions.max())
    if outside.any():
        log.warning(
            "%d of %d rows ask for focus beyond the stack's range %.4f-%.4f mm; "
            "they use the nearest end frame",
            int(outside.sum()),
            rows,
            positions.min(),
            positions.max(),
        )
    return weights.row_weights(positions, p_rows, outside="clamp")


def process_dof(
    paths: Sequence[str | Path] | str | Path,
    output: str | Path,
    target: DofTarget,
    options: StackOptions | None = None,
    *,
    progress: Progress = _no_progress,
) -> StackResult:
    """A flexible DOF from a focal stack -> ``output`` + ``output.json``.

    Parameters
    ----------
    paths : path, glob or sequence of paths
        A stack whose frames have absolute focus positions (stack.toml).
    output : path
        ``.tif``, ``.png`` or ``.jpg``; the sidecar is ``output`` + ``.json``.
    target : DofTarget
        What should be in focus.
    options : StackOptions, optional
        ``lens``, ``align``, ``encoding`` are used (no deconvolution).
    progress : callable(stage, done, total), optional

    Returns
    -------
    StackResult
    """
    options = StackOptions() if options is None else options
    output = Path(output)
    check_output(output)
    stack, lens, start = load(paths, options)
    if lens is None:
        raise InputError(
            f"{stack.base_dir}: no lens profile: set lens in stack.toml or pass --lens"
        )
    aligned = align_stack(stack, lens, options, start, progress=progress)
    stack = aligned.stack  # in focus order, without blank frames
    if not aligned.absolute:
        raise InputError(
            f"{stack.base_dir}: flexdof dof needs each frame's absolute focus position "
            "(focus_distance_mm or image_distance_mm in stack.toml)"
        )
    w = frame_weights(target, lens, aligned.positions, aligned.shape[0])
    normalise_exposure(aligned, w, options)  # a drifting exposure would band the rows' DOFs
    image = accumulate(aligned, w, options, progress=progress)[0]
    sidecar = stack_sidecar(aligned, w, f"dof-{target.kind}", options)
    sidecar["dof"] = {
        "target": target.kind,
        "in_focus_mm": [list(r) for r in target.in_focus],
        "fractions": list(target.fractions) if target.fractions else None,
        "tilt_deg": target.tilt_deg,
        "at_mm": target.at_mm,
        "rows_csv": str(target.rows_csv) if target.rows_csv else None,
        "frames_used": int(np.count_nonzero(w.reshape(-1, len(stack)).max(axis=0) > 0)),
    }
    if w.ndim == 2:
        sidecar["dof"]["row_weights"] = "per-row weights; a frame's 'weight' is its mean over rows"
    return write_result(
        output, image, None, sidecar, aligned.timings, start, options, stack.files
    )
