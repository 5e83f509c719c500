"""``flexdof psf``: an EDOF integrated PSF (Eqs. 5-7) as a kernel file and a Fig. 3-style plot."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from pipeline.commands import print_json
from pipeline.core import psf
from pipeline.errors import InputError
from pipeline.io.profiles import load_lens
from pipeline.jobs.sweep import profile_from_range


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "psf",
        help="integrated PSF of a constant-speed sweep: kernel file and PSF-vs-IPSF plot",
        description="Build the IPSF of a detector sweeping --near..--far at constant speed "
        "(Sec. 4.1) for a scene depth, save it as .npy or .tif, and plot normal-camera PSFs "
        "against EDOF IPSFs over depth (Fig. 3).",
    )
    parser.add_argument(
        "--lens", default="fujinon-12.5mm-f1.4-sony-1-3in", help="profile name or path"
    )
    parser.add_argument("--near", type=float, default=446.53, help="near end of the sweep, mm")
    parser.add_argument("--far", type=float, default=math.inf, help="far end of the sweep, mm")
    parser.add_argument("--exposure", type=float, default=0.36, help="exposure time T, s")
    parser.add_argument("--depth", type=float, default=750.0, help="scene depth of the kernel, mm")
    parser.add_argument("--model", choices=("pillbox", "gaussian"), help="lens PSF (Eq. 3 / 4)")
    parser.add_argument("--size", type=int, help="odd kernel size (default: from the blur)")
    parser.add_argument("--method", choices=("auto", "analytic", "numeric"), default="auto")
    parser.add_argument("-o", "--output", type=Path, help="kernel file (.npy or .tif)")
    parser.add_argument("--plot", type=Path, help="PNG of PSFs vs IPSFs over depth (Fig. 3)")
    parser.add_argument("--json", action="store_true", help="machine-readable summary")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    lens = load_lens(args.lens)
    profile = profile_from_range(lens, args.near, args.far, args.exposure)
    start, end = profile.start_mm, profile.end_mm
    kernel = psf.integrated_psf(
        lens, args.depth, profile, model=args.model, size=args.size, method=args.method
    )
    if args.output is not None:
        save_kernel(args.output, kernel)
    if args.plot is not None:
        from pipeline.paper import figures

        figures.psf_vs_ipsf_figure(lens, profile, args.plot, model=args.model)
    summary = {
        "lens": lens.name,
        "sweep_image_distance_mm": [start, end],
        "speed_mm_s": (end - start) / args.exposure,
        "depth_mm": args.depth,
        "size": kernel.shape[0],
        "peak": float(kernel.max()),
        "output": str(args.output) if args.output else None,
    }
    if args.json:
        print_json(summary)
    else:
        print(
            f"IPSF of {lens.name} sweeping {start:.4f} -> {end:.4f} mm in {args.exposure} s "
            f"at depth {args.depth} mm: {kernel.shape[0]}x{kernel.shape[1]} px, "
            f"peak {kernel.max():.4g}"
        )
    return 0


def save_kernel(path: Path, kernel: np.ndarray) -> None:
    """Write a kernel as .npy (float64) or .tif (float32), atomically."""
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
