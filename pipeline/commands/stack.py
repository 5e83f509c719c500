"""``flexdof stack``: focal stack or sweep capture -> extended-DOF image (Sec. 9, Sec. 4)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands import _flags


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "stack",
        help="focal stack or sweep capture -> extended-DOF image (the main job)",
        description="Align the frames (focus breathing), average them with weights that "
        "emulate a constant-speed focus sweep (Sec. 9) and deconvolve the average with its "
        "depth-independent integrated PSF. A directory with stack.toml of kind 'sweep' is "
        "deconvolved with the IPSF of its motion (Sec. 4, 8). `flexdof sample-path` prints "
        "where the shipped sample stack is.",
    )
    parser.add_argument("paths", nargs="+", help="a stack directory, a glob, or frame files")
    _flags.add_output(
        parser, "extended-DOF image (.tif, .png or .jpg); OUTPUT.json beside it", encoding=True
    )
    parser.add_argument(
        "--save-kernel", type=Path, metavar="TIF", help="also write the IPSF as a float32 TIFF"
    )
    _flags.add_processing(parser)
    _flags.add_json(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.commands import print_json
    from pipeline.commands._progress import stage_progress
    from pipeline.jobs.stack import process_stack
    from pipeline.parallel.scheduler import scheduler_context

    options = _flags.stack_options(args)
    with (
        scheduler_context(args.scheduler, args.threads),
        stage_progress(enabled=not args.quiet and not args.json) as progress,
    ):
        result = process_stack(args.paths, args.output, options, progress=progress)
    kernel = result.sidecar["kernel"]
    timings = result.sidecar["timings_s"]
    if args.json:
        print_json(
            {
                "output": str(result.output),
                "sidecar": f"{result.output}.json",
                "frames": len(result.sidecar.get("frames", [])),
                "left_out": result.sidecar.get("left_out", []),
                "method": options.method,
                "kernel": {"source": kernel["source"], "size": kernel["size"]},
                "timings_s": timings,
            }
        )
    elif not args.quiet:
        print(
            f"wrote {result.output} ({kernel['source']} kernel "
            f"{kernel['size']} px, {options.method}) in {timings['total']:.1f} s"
        )
    return 0
