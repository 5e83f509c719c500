"""``flexdof simulate``: render a capture of a scene (radiance image + depth map)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from pipeline.core import optics, simulate
from pipeline.core.motion import Profile
from pipeline.core.scene import Camera, Exposure, Scene
from pipeline.errors import InputError
from pipeline.io import profiles, read, write

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="render a normal, focus-sweep or rolling-shutter capture of a scene",
        description=(
            "Render a capture of SCENE: a directory holding ground_truth.tif and depth_mm.npy "
            "(as stacks/motorcycle/), or an image file with --depth. The plan (which effects "
            "are simulated, and why) is printed with --explain."
        ),
    )
    p.add_argument("scene", nargs="+", metavar="SCENE", help="scene directory or image file")
    p.add_argument("--depth", type=Path, help="depth map (.npy, mm) for an image SCENE")
    p.add_argument("--lens", required=True, help="lens profile name or path")
    focus = p.add_mutually_exclusive_group(required=True)
    focus.add_argument("--focus-mm", type=float, help="normal capture focused at this depth")
    focus.add_argument("--image-distance-mm", type=float, help="normal capture at this p")
    focus.add_argument(
        "--sweep-mm",
        type=float,
        nargs=2,
        metavar=("NEAR", "FAR"),
        help="constant-speed sweep of the focal plane between two depths (mm, 'inf' allowed)",
    )
    p.add_argument("--exposure-s", type=float, default=0.1, help="exposure time (default 0.1)")
    p.add_argument("--shutter", choices=("global", "rolling"), help="default: the lens's")
    p.add_argument("--electrons", type=float, help="electrons at radiance 1 (enables noise)")
    p.add_argument("--read-noise", type=float, default=0.0, help="read noise, electrons")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--tolerance", type=float, default=1e-3, help="effect tolerance (1e-3)")
    p.add_argument("--missing-depth", choices=("fill", "exclude"), help="for NaN depth pixels")
    p.add_argument("--explain", action="store_true", help="print the plan")
    p.add_argument("--plan-only", action="store_true", help="print the plan, render nothing")
    p.add_argument("-o", "--output", type=Path, help="output image (one SCENE only)")
    p.set_defaults(func=run)


def _load_scene(path: Path, depth: Path | None, missing: str | None) -> Scene:
    if path.is_dir():
        image_path, depth = path / "ground_truth.tif", depth or path / "depth_mm.npy"
    else:
        image_path = path
        if depth is None:
            raise InputError(f"{path}: an image SCENE needs --depth DEPTH.npy")
    try:
        depth_mm = np.load(depth)
    except (OSError, ValueError) as err:
        raise InputError(f"{depth}: cannot read the depth map as .npy: {err}") from err
    return Scene.from_depth(read.read_frame(image_path), depth_mm, missing_depth=missing)


def _camera(args, lens) -> Camera:
    exposure = None
    if args.electrons is not None:
        exposure = Exposure(args.electrons, args.read_noise)
    options = {"exposure": exposure, "shutter": args.shutter}
    f = lens.focal_length_mm
    if args.sweep_mm is not None:
        near, far = args.sweep_mm
        v0, v1 = optics.image_distance(f, far), optics.image_distance(f, near)
        if args.exposure_s <= 0:
            raise InputError(f"--exposure-s must be > 0, got {args.exposure_s}")
        return Camera(lens, Profile([0.0, args.exposure_s], [v0, v1]), **options)
    p = args.image_distance_mm
    if p is None:
        p = optics.image_distance(f, args.focus_mm)
    return Camera.static(lens, p, args.exposure_s, **options)


def run(args: argparse.Namespace) -> int:
    if args.output is not None and len(args.scene) > 1:
        raise InputError("-o/--output takes one SCENE; give one scene or omit -o")
    lens = profiles.load_lens(args.lens)
    camera = _camera(args, lens)
    for name in args.scene:
        path = Path(name)
        scene = _load_scene(path, args.depth, args.missing_depth)
        plan = simulate.plan(scene, camera, tolerance=args.tolerance)
        if args.explain or args.plan_only:
            print(f"{path}:")
            print(plan.explain())
        if args.plan_only:
            continue
        image = simulate.render(scene, camera, plan_=plan, seed=args.seed)
        out = args.output or path.with_name(f"{path.stem}_simulated.tif")
        write.write_image(out, image, encoding="float32")
        log.info("wrote %s", out)
    return 0
