"""``flexdof dof``: a flexible DOF synthesised from a focal stack (Secs. 5-7 via Sec. 9)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands import _flags


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "dof",
        help="synthesise a discontinuous, tilted or non-planar DOF from a focal stack",
        description="Average the aligned frames of a focal stack with weights that emulate "
        "a detector dwelling on chosen depth ranges (Sec. 5), a tilted focal plane (Sec. 6) "
        "or a per-row focal surface (Sec. 7). Needs absolute focus positions (stack.toml). "
        "A range end within 1%% beyond the stack's end frame is clamped to it.",
    )
    parser.add_argument("paths", nargs="+", help="stack directory, stack.toml or frame files")
    _flags.add_output(parser, "image (.tif, .png or .jpg); OUTPUT.json beside it", encoding=True)
    target = parser.add_argument_group("DOF target (choose one)")
    target.add_argument(
        "--in-focus",
        action="append",
        metavar="NEAR:FAR",
        help="depth range in focus, mm (FAR may be inf; NEAR=FAR pauses at one depth); "
        "repeatable",
    )
    target.add_argument(
        "--fraction",
        action="append",
        type=float,
        help="time share of each --in-focus range, in order (default: equal shares)",
    )
    target.add_argument(
        "--tilt-deg", type=float, help="focal-plane tilt about the horizontal axis, degrees"
    )
    target.add_argument(
        "--at-mm", type=float, help="depth of the tilted plane at the image centre, mm"
    )
    target.add_argument(
        "--rows", type=Path, metavar="CSV", help="CSV of (row, depth_mm) knots: non-planar DOF"
    )
    _flags.add_alignment(parser)
    _flags.add_match_exposure(parser)
    _flags.add_crop(parser)
    _flags.add_compute(parser)
    _flags.add_json(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.commands import print_json
    from pipeline.commands._progress import stage_progress
    from pipeline.jobs.dof import DofTarget, parse_range, process_dof
    from pipeline.parallel.scheduler import scheduler_context

    target = DofTarget(
        in_focus=tuple(parse_range(t) for t in args.in_focus or ()),
        fractions=tuple(args.fraction) if args.fraction else None,
        tilt_deg=args.tilt_deg,
        at_mm=args.at_mm,
        rows_csv=args.rows,
    )
    options = _flags.stack_options(args)
    with (
        scheduler_context(args.scheduler, args.threads),
        stage_progress(enabled=not args.quiet and not args.json) as progress,
    ):
        result = process_dof(args.paths, args.output, target, options, progress=progress)
    dof = result.sidecar["dof"]
    summary = {
        "output": str(result.output),
        "target": target.kind,
        "frames_used": dof["frames_used"],
        "frames": len(result.sidecar["frames"]),
        "left_out": result.sidecar["left_out"],
    }
    if args.json:
        print_json(summary)
    elif not args.quiet:
        print(
            f"{target.kind} DOF from {summary['frames_used']} of {summary['frames']} frames "
            f"-> {result.output}"
        )
    return 0
