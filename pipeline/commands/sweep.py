"""``flexdof sweep``: deconvolve focus-sweep captures, image sequences or EDOF video (Sec. 4, 8)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from pipeline.commands import _flags


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sweep",
        help="deconvolve a focus-sweep capture, a sequence of them, or an EDOF video",
        description="Deconvolve images captured while the focus swept --far-mm..--near-mm at "
        "constant speed (Sec. 4, 8) with the IPSF of that motion (Eq. 6/7). Several images "
        "(or a video whose frames sweep alternately forward and back, Sec. 4.2) are "
        "deconvolved in parallel.",
    )
    parser.add_argument("inputs", nargs="+", type=Path, help="sweep image(s) or one video")
    _flags.add_output(
        parser,
        "image (one input), folder (several) or video (.mp4/.avi)",
        encoding=True,
    )
    _flags.add_lens(parser, required=True)
    _flags.add_depth_range(parser, far=math.inf, required=True)
    _flags.add_exposure(parser, 1.0, "exposure time of each capture, s")
    _flags.add_method(parser, methods=_flags.SINGLE_IMAGE_METHODS)
    _flags.add_compute(parser)
    _flags.add_json(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.commands import print_json
    from pipeline.commands._progress import stage_progress
    from pipeline.errors import InputError
    from pipeline.io.profiles import load_lens
    from pipeline.jobs.sweep import (
        VIDEO_EXTENSIONS,
        process_sweep_image,
        process_sweep_sequence,
        process_sweep_video,
        profile_from_range,
    )
    from pipeline.parallel.scheduler import scheduler_context

    lens = load_lens(args.lens)
    profile = profile_from_range(lens, args.near_mm, args.far_mm, args.exposure_s)
    options = _flags.stack_options(args)
    with (
        scheduler_context(args.scheduler, args.threads),
        stage_progress(enabled=not args.quiet and not args.json) as progress,
    ):
        if len(args.inputs) == 1 and args.inputs[0].suffix.lower() in VIDEO_EXTENSIONS:
            if args.output.suffix.lower() not in VIDEO_EXTENSIONS:
                raise InputError(f"output {args.output}: a video input needs a .mp4 or .avi output")
            count = process_sweep_video(
                args.inputs[0], lens, profile, args.output, options, progress=progress
            )
            outputs, text = [args.output], f"wrote {args.output} ({count} frames)"
        elif len(args.inputs) == 1:
            result = process_sweep_image(
                args.inputs[0], lens, profile, args.output, options, progress=progress
            )
            outputs, text = [result.output], f"wrote {result.output}"
        else:
            outputs = process_sweep_sequence(
                args.inputs, lens, profile, args.output, options, progress=progress
            )
            text = f"wrote {len(outputs)} images to {args.output}"
    if args.json:
        print_json(
            {
                "lens": lens.name,
                "near_mm": args.near_mm,
                "far_mm": args.far_mm,
                "exposure_s": args.exposure_s,
                "method": options.method,
                "outputs": [str(p) for p in outputs],
            }
        )
    elif not args.quiet:
        print(text)
    return 0
