"""``flexdof dof``: a flexible DOF synthesised from a focal stack (Secs. 5-7 via Sec. 9).

Discontinuous (``--in-focus NEAR:FAR``, repeatable), tilted (``--tilt-deg A --at-mm U``)
or non-planar (``--rows FILE.csv``) DOFs as weighted sums of the aligned frames
(:mod:`pipeline.weights`), an optical-style result: no deconvolution.
"""

from __future__ import annotations

import argparse
import csv
import logging
import math
import time
from pathlib import Path

import numpy as np

from pipeline import align, io, motion, optics, stack, weights
from pipeline.commands import print_json
from pipeline.errors import InputError
from pipeline.profiles import Lens, load_lens

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "dof",
        help="synthesise a discontinuous, tilted or non-planar DOF from a focal stack",
        description="Average the aligned frames of a focal stack with weights that emulate "
        "a detector dwelling on chosen depth ranges (Sec. 5), a tilted focal plane (Sec. 6) "
        "or a per-row focal surface (Sec. 7). Needs absolute focus positions (stack.toml).",
    )
    parser.add_argument("stack", nargs="+", help="stack directory, stack.toml or frame files")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output image")
    target = parser.add_argument_group("DOF target (choose one)")
    target.add_argument(
        "--in-focus",
        action="append",
        metavar="NEAR:FAR",
        help="depth range in focus, mm (FAR may be inf; NEAR=FAR pauses at one depth); "
        "repeatable",
    )
    target.add_argument(
        "--fraction", action="append", type=float, help="time share of each --in-focus range"
    )
    target.add_argument("--tilt-deg", type=float, help="focal-plane tilt about the horizontal axis")
    target.add_argument("--at-mm", type=float, help="depth of the tilted plane at the image centre")
    target.add_argument("--rows", type=Path, help="CSV of (row, depth_mm) knots: non-planar DOF")
    parser.add_argument("--lens", help="lens profile (default: the stack's)")
    parser.add_argument(
        "--align",
        choices=("auto", "analytic", "none"),
        default="auto",
        help="magnification compensation: estimated homographies (with the analytic scaling "
        "as fallback), the analytic scaling p_ref/p_i, or none",
    )
    parser.add_argument(
        "--encoding",
        choices=("srgb16", "linear16", "float32", "srgb8"),
        help="output encoding (default: the format's, see pipeline.io.write_image)",
    )
    parser.add_argument("--json", action="store_true", help="machine-readable summary")
    parser.set_defaults(func=run)


def parse_range(text: str) -> tuple[float, float]:
    """``"NEAR:FAR"`` (mm; ``inf`` allowed) -> (near, far)."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError(text)
        near, far = float(parts[0]), float(parts[1])
    except ValueError as err:
        raise InputError(f"--in-focus {text!r}: expected NEAR:FAR in mm, e.g. 450:600") from err
    if math.isnan(near) or math.isnan(far) or not 0 < near <= far:
        raise InputError(f"--in-focus {text!r}: need 0 < NEAR <= FAR (mm)")
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
            raise InputError(
                f"--rows {path}: line {k + 1} {line!r} is not 'row,depth_mm'"
            ) from err
    if not pairs:
        raise InputError(f"--rows {path}: no (row, depth_mm) lines")
    return np.array(pairs)


def _target(args: argparse.Namespace) -> str:
    given = [
        name
        for name, on in (
            ("in-focus", bool(args.in_focus)),
            ("tilt", args.tilt_deg is not None or args.at_mm is not None),
            ("rows", args.rows is not None),
        )
        if on
    ]
    if len(given) != 1:
        raise InputError(
            "give exactly one DOF target: --in-focus NEAR:FAR, --tilt-deg A --at-mm U, or "
            f"--rows FILE.csv (got {', '.join(given) or 'none'})"
        )
    if given[0] == "tilt" and (args.tilt_deg is None or args.at_mm is None):
        raise InputError("a tilted DOF needs both --tilt-deg and --at-mm")
    if args.fraction and given[0] != "in-focus":
        raise InputError("--fraction only applies to --in-focus ranges")
    return given[0]


def frame_weights(
    target: str, args: argparse.Namespace, lens: Lens, positions: np.ndarray, rows: int
) -> np.ndarray:
    """(n,) weights for a discontinuous DOF, (rows, n) for a tilted or non-planar one."""
    f = lens.focal_length_mm
    if target == "in-focus":
        depth_ranges = [parse_range(t) for t in args.in_focus]
        fractions = args.fraction or [1.0] * len(depth_ranges)
        if len(fractions) != len(depth_ranges):
            raise InputError(
                f"--fraction given {len(fractions)} times for {len(depth_ranges)} --in-focus "
                "ranges; give one per range or none (equal shares)"
            )
        image_ranges = [
            (float(optics.image_distance(f, far)), float(optics.image_distance(f, near)))
            for near, far in depth_ranges
        ]
        return weights.discontinuous_weights(positions, image_ranges, fractions)
    if target == "tilt":
        offsets = motion.row_offsets_mm(rows, lens.sensor_height_mm)
        p_rows = motion.tilted_row_image_distances(f, args.tilt_deg, args.at_mm, offsets)
    else:
        knot_rows, knot_p = motion.row_image_distances(f, read_rows_csv(args.rows), rows)
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


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    target = _target(args)
    stk = stack.load_stack(args.stack if len(args.stack) > 1 else args.stack[0])
    lens = load_lens(args.lens) if args.lens else stk.lens_profile
    if lens is None:
        raise InputError("no lens profile: set lens in stack.toml or pass --lens")
    found = stack.image_distances_mm(stk, lens)
    if found is None or found.relative:
        raise InputError(
            f"{stk.base_dir}: flexdof dof needs each frame's absolute focus position "
            "(focus_distance_mm or image_distance_mm in stack.toml)"
        )
    positions = np.asarray(found.image_distances_mm, dtype=np.float64)
    info = stack.check_frames(stk)
    shape = tuple(info.shape)
    w = frame_weights(target, args, lens, positions, shape[0])
    t_weights = time.perf_counter()

    analytic = align.analytic_alignment(positions, shape)
    if args.align == "auto":
        alignments = align.estimate_alignment(
            [lambda i=i: stk.read(i) for i in range(len(stk))], fallback=analytic
        )
    elif args.align == "analytic":
        alignments = analytic
    else:
        alignments = None
    t_align = time.perf_counter()

    used = np.flatnonzero(w.reshape(-1, len(stk)).max(axis=0) > 0)
    out = np.zeros(shape, dtype=np.float32)
    for i in used:
        frame = stk.read(int(i))
        if alignments is not None:
            frame = align.warp(frame, alignments[i].homography, shape)
        wi = w[i] if w.ndim == 1 else w[:, i].reshape((-1,) + (1,) * (frame.ndim - 1))
        out += (wi * frame).astype(np.float32)
    t_sum = time.perf_counter()
    io.write_image(args.output, out, encoding=args.encoding)
    sidecar = {
        "version": 1,
        "inputs": [str(p) for p in stk.files],
        "lens": lens.name,
        "method": f"dof-{target}",
        "frames": [
            {
                "file": str(stk.files[i]),
                "image_distance_mm": float(positions[i]),
                "weight": float(w[i] if w.ndim == 1 else w[:, i].mean()),
                "scale": 1.0 if alignments is None else alignments[i].scale,
                "homography": np.eye(3) if alignments is None else alignments[i].homography,
            }
            for i in range(len(stk))
        ],
        "timings_s": {
            "weights": t_weights - t0,
            "align": t_align - t_weights,
            "accumulate": t_sum - t_align,
            "total": time.perf_counter() - t0,
        },
    }
    if w.ndim == 2:
        sidecar["row_weights"] = "per-row weights; 'weight' is the mean over rows"
    io.write_json(args.output.with_suffix(".json"), sidecar)
    summary = {"output": str(args.output), "target": target, "frames_used": int(used.size)}
    if args.json:
        print_json(summary)
    else:
        print(f"{target} DOF from {used.size} of {len(stk)} frames -> {args.output}")
    return 0
