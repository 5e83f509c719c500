"""``flexdof sweep``: deconvolve focus-sweep captures, image sequences or EDOF video (Sec. 4, 8)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from pipeline.commands._progress import stage_progress
from pipeline.commands.stack import add_compute_options, options_from_args
from pipeline.errors import InputError
from pipeline.io.profiles import load_lens
from pipeline.jobs.options import METHODS
from pipeline.jobs.sweep import (
    VIDEO_EXTENSIONS,
    process_sweep_image,
    process_sweep_sequence,
    process_sweep_video,
    profile_from_range,
)
from pipeline.parallel.scheduler import scheduler_context

# issue 13: "sparse" is 100-160x slower than Wiener for +0.06-0.09 dB; not offered on the
# command line (pipeline.core.deconvolve still has it, for the accuracy benchmark and the API)
CLI_METHODS = tuple(m for m in METHODS if m != "sparse")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sweep",
        help="deconvolve a focus-sweep capture, a sequence of them, or an EDOF video",
        description="Deconvolve images captured while the focus swept --far..--near at constant "
        "speed (Sec. 4, 8) with the IPSF of that motion (Eq. 6/7). Several images (or a video "
        "whose frames sweep alternately forward and back, Sec. 4.2) are deconvolved in parallel.",
    )
    parser.add_argument("inputs", nargs="+", type=Path, help="sweep image(s) or one video")
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        required=True,
        help="image (one input), folder (several) or video (.mp4/.avi)",
    )
    encoding = parser.add_mutually_exclusive_group()
    encoding.add_argument("--linear", action="store_true", help="linear 16-bit TIFF")
    encoding.add_argument("--float", action="store_true", help="linear float32 TIFF")
    parser.add_argument("--lens", required=True, help="lens profile name or path")
    parser.add_argument("--near", type=float, required=True, help="near end of the sweep, mm")
    parser.add_argument("--far", type=float, default=math.inf, help="far end, mm (default inf)")
    parser.add_argument("--exposure", type=float, default=1.0, help="exposure time, s")
    parser.add_argument("--method", choices=CLI_METHODS, default="wiener", help="deconvolution")
    parser.add_argument("--tile-px", type=int, default=1024, help="deconvolution tile side")
    add_compute_options(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    lens = load_lens(args.lens)
    profile = profile_from_range(lens, args.near, args.far, args.exposure)
    options = options_from_args(args)
    say = print if not args.quiet else (lambda *_: None)
    with (
        scheduler_context(args.scheduler, args.threads),
        stage_progress(enabled=not args.quiet) as progress,
    ):
        if len(args.inputs) == 1 and args.inputs[0].suffix.lower() in VIDEO_EXTENSIONS:
            if args.output.suffix.lower() not in VIDEO_EXTENSIONS:
                raise InputError(f"output {args.output}: a video input needs a .mp4 or .avi output")
            count = process_sweep_video(
                args.inputs[0], lens, profile, args.output, options, progress=progress
            )
            say(f"wrote {args.output} ({count} frames)")
        elif len(args.inputs) == 1:
            result = process_sweep_image(
                args.inputs[0], lens, profile, args.output, options, progress=progress
            )
            say(f"wrote {result.output}")
        else:
            outputs = process_sweep_sequence(
                args.inputs, lens, profile, args.output, options, progress=progress
            )
            say(f"wrote {len(outputs)} images to {args.output}")
    return 0
