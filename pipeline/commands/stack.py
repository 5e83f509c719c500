"""``flexdof stack``: focal stack or sweep capture -> extended-DOF image (Sec. 9, Sec. 4)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from pipeline.commands._progress import stage_progress
from pipeline.jobs.options import ALIGN_MODES, METHODS, StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.scheduler import scheduler_context

# issue 13: "sparse" is 100-160x slower than Wiener for +0.06-0.09 dB; not offered on the
# command line (pipeline.core.deconvolve still has it, for the accuracy benchmark and the API)
CLI_METHODS = tuple(m for m in METHODS if m != "sparse")

log = logging.getLogger(__name__)


def add_output_options(parser: argparse.ArgumentParser) -> None:
    """``-o`` and its encoding: the flags of every command that writes an image."""
    parser.add_argument("-o", "--output", type=Path, required=True, help=".tif, .png or .jpg")
    encoding = parser.add_mutually_exclusive_group()
    encoding.add_argument("--linear", action="store_true", help="linear 16-bit TIFF")
    encoding.add_argument("--float", action="store_true", help="linear float32 TIFF")


def add_alignment_options(parser: argparse.ArgumentParser) -> None:
    """The lens and the magnification compensation: flags of every job over a focal stack."""
    parser.add_argument("--lens", help="lens profile name or path (default: from stack.toml)")
    parser.add_argument(
        "--align",
        choices=ALIGN_MODES,
        default="estimate",
        help="magnification compensation: estimated homographies, scaling from the focus "
        "positions, or none",
    )


def add_compute_options(parser: argparse.ArgumentParser) -> None:
    """Where the job runs."""
    parser.add_argument("--threads", type=int, help="local worker threads (default: all cores)")
    parser.add_argument("--scheduler", help="dask.distributed scheduler address (tcp://host:port)")


def add_processing_options(parser: argparse.ArgumentParser) -> None:
    """Flags shared by the commands that run the main job (stack, workflow)."""
    add_alignment_options(parser)
    parser.add_argument("--method", choices=CLI_METHODS, default="wiener", help="deconvolution")
    parser.add_argument(
        "--blur-span-px",
        type=float,
        help="blur (px) of a point focused at one end of the stack seen at the other end; "
        "estimated from the frames when there is no lens profile",
    )
    parser.add_argument("--tile-px", type=int, default=1024, help="deconvolution tile side")
    add_compute_options(parser)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "stack",
        help="focal stack or sweep capture -> extended-DOF image",
        description="Align the frames (focus breathing), average them with weights that "
        "emulate a constant-speed focus sweep (Sec. 9) and deconvolve the average with its "
        "depth-independent integrated PSF. A directory with stack.toml of kind 'sweep' is "
        "deconvolved with the IPSF of its motion (Sec. 4, 8).",
    )
    parser.add_argument("paths", nargs="+", help="a stack directory, a glob, or frame files")
    add_output_options(parser)
    parser.add_argument("--save-kernel", type=Path, help="write the IPSF as a float32 TIFF")
    add_processing_options(parser)
    parser.set_defaults(func=run)


def options_from_args(args: argparse.Namespace) -> StackOptions:
    encoding = "linear16" if getattr(args, "linear", False) else None
    if getattr(args, "float", False):
        encoding = "float32"
    defaults = StackOptions()
    return StackOptions(
        lens=getattr(args, "lens", None),
        method=getattr(args, "method", defaults.method),
        align=getattr(args, "align", defaults.align),
        encoding=encoding,
        blur_span_px=getattr(args, "blur_span_px", None),
        tile_px=getattr(args, "tile_px", defaults.tile_px),
        save_kernel=getattr(args, "save_kernel", None),
    )


def run(args: argparse.Namespace) -> int:
    options = options_from_args(args)
    with (
        scheduler_context(args.scheduler, args.threads),
        stage_progress(enabled=not args.quiet) as progress,
    ):
        result = process_stack(args.paths, args.output, options, progress=progress)
    timings = result.sidecar["timings_s"]
    if not args.quiet:
        print(
            f"wrote {result.output} ({result.sidecar['kernel']['source']} kernel "
            f"{result.sidecar['kernel']['size']} px, {options.method}) in {timings['total']:.1f} s"
        )
    return 0
