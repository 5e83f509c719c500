"""``flexdof optics``: sweep geometry for a lens and depth ranges (Fig. 2)."""

from __future__ import annotations

import argparse
import math

from pipeline.commands import _flags

FIG2_RANGES = ((1000.0, math.inf), (500.0, math.inf), (200.0, 500.0))


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "optics",
        help="detector translation and image shift for sweeping a depth range (Fig. 2)",
        description="Sweep geometry like the paper's Fig. 2. Without --near-mm/--far-mm, "
        "prints Fig. 2's three depth ranges.",
    )
    _flags.add_lens(parser, default=_flags.DEFAULT_LENS)
    _flags.add_depth_range(parser, what="the depth range (default: Fig. 2's ranges)")
    parser.add_argument(
        "--coc-um",
        type=float,
        default=14.1,
        metavar="UM",
        help="circle of confusion of the normal camera's DOF, um",
    )
    _flags.add_json(parser)
    parser.set_defaults(func=run)


def sweep_geometry(lens, near_mm: float, far_mm: float, coc_um: float) -> dict:
    """Fig. 2's columns plus the sweep's end positions and the normal camera's DOF."""
    from pipeline.core import optics

    translation = optics.sweep_translation(lens.focal_length_mm, near_mm, far_mm)
    start = optics.image_distance(lens.focal_length_mm, far_mm)
    mid_focus = optics.focus_distance(lens.focal_length_mm, start + translation / 2)
    dof = optics.depth_of_field(lens.focal_length_mm, lens.f_number, mid_focus, coc_um * 1e-3)
    return {
        "near_mm": near_mm,
        "far_mm": far_mm,
        "translation_um": translation * 1e3,
        "start_image_distance_mm": start,
        "end_image_distance_mm": start + translation,
        "max_image_shift_px": optics.image_position_change_px(
            lens.focal_length_mm,
            near_mm,
            far_mm,
            width_px=lens.width_px,
            height_px=lens.height_px,
        ),
        "min_sweep_time_s": translation / lens.max_speed_mm_s,
        "normal_dof_at_mid_mm": list(dof),
    }


def run(args: argparse.Namespace) -> int:
    from pipeline.commands import print_json
    from pipeline.io.profiles import load_lens

    lens = load_lens(args.lens)
    if (args.near_mm is None) != (args.far_mm is None):
        raise ValueError("give both --near-mm and --far-mm, or neither for Fig. 2's ranges")
    ranges = FIG2_RANGES if args.near_mm is None else ((args.near_mm, args.far_mm),)
    rows = [sweep_geometry(lens, near, far, args.coc_um) for near, far in ranges]
    if args.json:
        print_json({"lens": lens.name, "rows": rows})
        return 0
    print(f"{lens.name}: f = {lens.focal_length_mm} mm, f/{lens.f_number}")
    print(
        f"{'depth range':>20}  {'translation':>12}  {'image shift':>11}  "
        f"{'sweep from -> to (mm)':>22}"
    )
    for row in rows:
        span = f"{row['near_mm']:.0f} - {row['far_mm']:.0f} mm"
        ends = f"{row['start_image_distance_mm']:.4f} -> {row['end_image_distance_mm']:.4f}"
        print(
            f"{span:>20}  {row['translation_um']:>9.1f} um  {row['max_image_shift_px']:>8.1f} px"
            f"  {ends:>22}"
        )
    return 0
