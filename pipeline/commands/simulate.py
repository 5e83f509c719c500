"""``flexdof simulate``: render a capture of a scene (radiance image + depth map)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.commands import _flags


class _SweepMm(argparse.Action):
    """The old ``--sweep-mm NEAR FAR``: sets ``--near-mm`` and ``--far-mm``."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        namespace.near_mm, namespace.far_mm = values


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="render a normal, focus-sweep or rolling-shutter capture of a scene",
        description=(
            "Render a capture of SCENE: a directory holding ground_truth.tif and depth_mm.npy "
            "(as the shipped sample, see `flexdof sample-path`), or an image file with "
            "--depth. A normal capture with --focus-mm or --image-distance-mm; a "
            "constant-speed focus sweep with --near-mm and --far-mm. The plan (which effects "
            "are simulated, and why) is printed with --explain."
        ),
    )
    p.add_argument("scene", nargs="+", metavar="SCENE", help="scene directory or image file")
    p.add_argument(
        "--depth", type=Path, metavar="NPY", help="depth map (.npy, mm) of an image SCENE"
    )
    _flags.add_lens(p, required=True)
    focus = p.add_argument_group("focus (one of: --focus-mm, --image-distance-mm, or a sweep)")
    focus.add_argument(
        "--focus-mm", type=float, metavar="MM", help="normal capture focused at this depth, mm"
    )
    focus.add_argument(
        "--image-distance-mm",
        type=float,
        metavar="MM",
        help="normal capture with the detector at this image distance p, mm",
    )
    _flags.add_depth_range(focus, what="a constant-speed sweep of the focal plane")
    focus.add_argument(
        "--sweep-mm", nargs=2, type=float, action=_SweepMm, help=argparse.SUPPRESS
    )
    _flags.add_exposure(p, 0.1, "exposure time, s")
    p.add_argument(
        "--shutter",
        choices=("global", "rolling"),
        help="shutter (default: the lens profile's sensor)",
    )
    p.add_argument(
        "--electrons", type=float, help="electrons at radiance 1 (enables shot and read noise)"
    )
    p.add_argument("--read-noise", type=float, default=0.0, help="read noise, electrons")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument(
        "--tolerance",
        type=float,
        default=1e-3,
        help="largest error an effect may cause before it is simulated",
    )
    p.add_argument(
        "--missing-depth",
        choices=("fill", "exclude"),
        help="what to do with NaN depth pixels (default: refuse them)",
    )
    p.add_argument("--explain", action="store_true", help="print the plan, then render")
    p.add_argument("--plan-only", action="store_true", help="print the plan, render nothing")
    _flags.add_output(
        p,
        "output image, float32 linear TIFF (one SCENE only; default: SCENE_simulated.tif)",
        required=False,
    )
    _flags.add_json(p)
    p.set_defaults(func=run)


def _load_scene(path: Path, depth: Path | None, missing: str | None):
    import numpy as np

    from pipeline.core.scene import Scene
    from pipeline.errors import InputError
    from pipeline.io import read

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


def _camera(args, lens):
    from pipeline.core import optics
    from pipeline.core.motion import Profile
    from pipeline.core.scene import Camera, Exposure
    from pipeline.errors import InputError

    given = [
        name
        for name, value in (
            ("--focus-mm", args.focus_mm),
            ("--image-distance-mm", args.image_distance_mm),
            ("--near-mm/--far-mm", args.near_mm if args.near_mm is not None else args.far_mm),
        )
        if value is not None
    ]
    if len(given) != 1:
        raise InputError(
            "give one focus: --focus-mm, --image-distance-mm, or a sweep --near-mm N --far-mm F"
            f" (got {', '.join(given) or 'none'})"
        )
    exposure = None
    if args.electrons is not None:
        exposure = Exposure(args.electrons, args.read_noise)
    options = {"exposure": exposure, "shutter": args.shutter}
    f = lens.focal_length_mm
    if given[0] == "--near-mm/--far-mm":
        if args.near_mm is None or args.far_mm is None:
            raise InputError("a sweep needs both --near-mm and --far-mm")
        v0, v1 = optics.image_distance(f, args.far_mm), optics.image_distance(f, args.near_mm)
        if args.exposure_s <= 0:
            raise InputError(f"--exposure-s must be > 0, got {args.exposure_s}")
        return Camera(lens, Profile([0.0, args.exposure_s], [v0, v1]), **options)
    p = args.image_distance_mm
    if p is None:
        p = optics.image_distance(f, args.focus_mm)
    return Camera.static(lens, p, args.exposure_s, **options)


def run(args: argparse.Namespace) -> int:
    from pipeline.commands import print_json
    from pipeline.commands._progress import stage_progress
    from pipeline.core import simulate
    from pipeline.errors import InputError
    from pipeline.io import profiles, write

    if args.output is not None and len(args.scene) > 1:
        raise InputError("-o/--output takes one SCENE; give one scene or omit -o")
    lens = profiles.load_lens(args.lens)
    camera = _camera(args, lens)
    results = []
    show_plan = (args.explain or args.plan_only) and not args.json
    for name in args.scene:
        path = Path(name)
        scene = _load_scene(path, args.depth, args.missing_depth)
        plan = simulate.plan(scene, camera, tolerance=args.tolerance)
        if show_plan:
            print(f"{path}:")
            print(plan.explain())
        entry = {"scene": str(path), "plan": plan.explain()}
        if not args.plan_only:
            with stage_progress(enabled=not args.quiet and not args.json) as progress:
                image = simulate.render(
                    scene,
                    camera,
                    plan_=plan,
                    seed=args.seed,
                    progress=lambda done, total, name=path.name: progress(name, done, total),
                )
            out = args.output or path.with_name(f"{path.stem}_simulated.tif")
            write.write_image(out, image, encoding="float32")
            entry["output"] = str(out)
            if not args.quiet and not args.json:
                print(f"wrote {out}")
        results.append(entry)
    if args.json:
        print_json({"lens": lens.name, "scenes": results})
    return 0
