"""``flexdof psf``: an EDOF integrated PSF (Eqs. 5-7) as a kernel file and a Fig. 3-style plot."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from pipeline.commands import _flags


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "psf",
        help="integrated PSF of a constant-speed sweep: kernel file and PSF-vs-IPSF plot",
        description="Build the IPSF of a detector sweeping --near-mm..--far-mm at constant speed "
        "(Sec. 4.1) for a scene depth, save it as .npy or .tif, and plot normal-camera PSFs "
        "against EDOF IPSFs over depth (Fig. 3).",
    )
    _flags.add_lens(parser, default=_flags.DEFAULT_LENS)
    _flags.add_depth_range(parser, near=446.53, far=math.inf)
    _flags.add_exposure(parser, 0.36, "exposure time T of the sweep, s")
    parser.add_argument(
        "--depth-mm",
        type=float,
        default=750.0,
        metavar="MM",
        help="scene depth the kernel is for, mm",
    )
    parser.add_argument(
        "--model",
        choices=("pillbox", "gaussian"),
        help="lens PSF: Eq. 3 pillbox or Eq. 4 Gaussian (default: the lens profile's)",
    )
    parser.add_argument(
        "--size", type=int, metavar="PX", help="odd kernel side (default: from the blur)"
    )
    parser.add_argument(
        "--method",
        choices=("auto", "analytic", "numeric"),
        default="auto",
        help="IPSF: analytic Eqs. 6/7, numeric quadrature of Eq. 5, or auto (analytic "
        "when the motion allows)",
    )
    _flags.add_output(parser, "kernel file (.npy or .tif)", required=False)
    parser.add_argument(
        "--plot",
        type=Path,
        metavar="PNG",
        help="also plot normal-camera PSFs vs IPSFs over depth (Fig. 3); needs the "
        "'plots' extra",
    )
    _flags.add_json(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.commands import print_json
    from pipeline.core import psf
    from pipeline.io.profiles import load_lens
    from pipeline.jobs.sweep import profile_from_range

    lens = load_lens(args.lens)
    profile = profile_from_range(lens, args.near_mm, args.far_mm, args.exposure_s)
    start, end = profile.start_mm, profile.end_mm
    kernel = psf.integrated_psf(
        lens, args.depth_mm, profile, model=args.model, size=args.size, method=args.method
    )
    if args.output is not None:
        save_kernel(args.output, kernel)
    if args.plot is not None:
        _flags.require_matplotlib("psf --plot")
        from pipeline.paper import figures

        figures.psf_vs_ipsf_figure(lens, profile, args.plot, model=args.model)
    summary = {
        "lens": lens.name,
        "sweep_image_distance_mm": [start, end],
        "speed_mm_s": (end - start) / args.exposure_s,
        "depth_mm": args.depth_mm,
        "size": kernel.shape[0],
        "peak": float(kernel.max()),
        "output": str(args.output) if args.output else None,
        "plot": str(args.plot) if args.plot else None,
    }
    if args.json:
        print_json(summary)
    else:
        print(
            f"IPSF of {lens.name} sweeping {start:.4f} -> {end:.4f} mm in {args.exposure_s} s "
            f"at depth {args.depth_mm} mm: {kernel.shape[0]}x{kernel.shape[1]} px, "
            f"peak {kernel.max():.4g}"
        )
    return 0


def save_kernel(path: Path, kernel) -> None:
    """Write a kernel as .npy (float64) or .tif (float32), atomically."""
    import numpy as np

    from pipeline.errors import InputError
    from pipeline.io.write import write_image

    suffix = path.suffix.lower()
    if suffix == ".npy":
        tmp = path.with_name(f".{path.name}.tmp.npy")
        np.save(tmp, kernel)
        tmp.replace(path)
    elif suffix in (".tif", ".tiff"):
        write_image(path, kernel.astype(np.float32), encoding="float32")
    else:
        raise InputError(f"--output {path}: use a .npy or .tif file name for the kernel")
