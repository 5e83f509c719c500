"""``flexdof tether``: list cameras, capture focal stacks and sweeps, calibrate focus steps."""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

from pipeline.commands import print_json
from pipeline.commands._flags import add_json
from pipeline.errors import InputError

log = logging.getLogger(__name__)


def register(subparsers) -> None:
    parser = subparsers.add_parser("tether", help="tethered capture over USB (PTP)")
    sub = parser.add_subparsers(dest="tether_command", metavar="ACTION")
    sub.required = True

    def common(p):
        add_json(p)
        p.add_argument("--emulate", choices=("canon", "nikon", "none"),
                       help="use the built-in emulated camera instead of USB (none: a bus "
                            "without a camera)")
        p.add_argument("--personality", metavar="NAME",
                       help="emulated body: eos-dslr (default canon), eos-r, eos-m, eos-sweep "
                            "(drives while exposing), nikon-dslr (default nikon)")

    p = sub.add_parser("list", help="list cameras and what they support")
    common(p)
    p.set_defaults(func=_list)

    p = sub.add_parser("stack", help="capture a focal stack by driving the focus")
    common(p)
    p.add_argument("-o", "--output", required=True, type=Path, help="output directory")
    p.add_argument("--frames", required=True, type=int, help="number of frames to capture")
    p.add_argument("--step", required=True, type=int, help="drive steps between frames")
    p.add_argument("--direction", choices=("near", "far"), default="far",
                   help="which way the focus is driven from the first frame")
    p.add_argument("--settle-ms", type=float, default=200.0, help="wait after each drive")
    p.add_argument("--drive-size", type=int, default=1, choices=(1, 2, 3),
                   help="Canon DriveLens step size (1 fine .. 3 coarse)")
    p.add_argument("--drive-pace-ms", type=float,
                   help="least time between focus-drive commands (Canon default 100/200/400 "
                        "ms for size 1/2/3)")
    p.add_argument("--lens", help="lens profile name or path written to stack.toml "
                                  "(required for a real camera)")
    p.set_defaults(func=_stack)

    p = sub.add_parser("sweep", help="one bulb exposure while driving the focus (Sec. 8)")
    common(p)
    p.add_argument("-o", "--output", required=True, type=Path, help="output directory")
    p.add_argument("--steps", required=True, type=int, help="total drive steps in the exposure")
    p.add_argument("--exposure-s", "--exposure", dest="exposure", required=True, type=float,
                   metavar="S", help="exposure time, s")
    p.add_argument("--direction", choices=("near", "far"), default="far",
                   help="which way the focus is driven during the exposure")
    p.add_argument("--period-ms", type=float, default=50.0, help="time between drive commands")
    p.add_argument("--fallback-step", type=int, default=10,
                   help="frame spacing of the dense stack used if the camera refuses")
    p.add_argument("--drive-size", type=int, default=1, choices=(1, 2, 3),
                   help="focus-drive command size (must match the calibration's)")
    p.add_argument("--drive-pace-ms", type=float, help="least time between drive commands")
    p.add_argument("--lens", help="lens profile name or path (required for a real camera)")
    p.set_defaults(func=_sweep)

    p = sub.add_parser("calibrate", help="measure step -> image distance from a captured stack")
    p.add_argument("stack", type=Path, help="stack directory with stack.toml (focus_step)")
    add_json(p)
    p.add_argument("--lens", required=True, help="lens profile to extend")
    p.add_argument("-o", "--output", required=True, type=Path, help="profile TOML to write")
    p.add_argument("--reference-focus-distance-mm", type=float, default=math.inf,
                   help="focus distance of the first frame (default: infinity)")
    p.set_defaults(func=_calibrate)


def _backend(args, *, bulb: bool = False):
    if not args.emulate:
        if args.personality:
            raise InputError("--personality needs --emulate")
        return None
    from pipeline.tether.emulated.device import emulated_backend

    if args.emulate == "none":
        return emulated_backend(None)
    return emulated_backend(args.emulate, args.personality, shutter="bulb" if bulb else "normal")


def _pace(args) -> float | None:
    if args.drive_pace_ms is None:
        return None
    if not (math.isfinite(args.drive_pace_ms) and args.drive_pace_ms >= 0):
        raise InputError(f"--drive-pace-ms must be >= 0, got {args.drive_pace_ms}")
    return args.drive_pace_ms / 1e3


def _lens(args):
    """(name for stack.toml, profile): --lens, or the emulated body's lens (``lens.toml``)."""
    from pipeline.io.profiles import lens_to_toml, load_lens

    if args.lens:
        return args.lens, load_lens(args.lens)  # fails early on an unknown profile
    if args.emulate in ("canon", "nikon"):
        from pipeline.tether.emulated.scene import LENS
        from pipeline.tether.flows import write_atomic

        args.output.mkdir(parents=True, exist_ok=True)
        write_atomic(args.output / "lens.toml", lens_to_toml(LENS))
        return "lens.toml", LENS
    raise InputError("--lens is required with a real camera: give the lens profile (a name "
                     "from lens_profiles/ or a path) that stack.toml should name")


def _list(args) -> int:
    from pipeline.tether.capabilities import body_capability
    from pipeline.tether.clock import SYSTEM_CLOCK
    from pipeline.tether.session import PtpSession
    from pipeline.tether.transport import UsbTransport, find_cameras, no_camera_message

    backend = _backend(args)
    cameras, seen = find_cameras(backend)
    say = (lambda *_: None) if args.json else print
    say(f"USB devices: {len(seen)}; PTP cameras: {len(cameras)}")
    if not cameras:
        say(no_camera_message(seen))
    found = []
    for device in cameras:
        session = PtpSession(UsbTransport(device), clock=getattr(backend, "clock", SYSTEM_CLOCK))
        try:
            info = session.open()
            cap = body_capability(info)  # the decision the stack and sweep commands apply
            stack = "yes" if cap.stack else f"no ({cap.stack_reason})"
            sweep = "yes" if cap.sweep else f"no ({cap.sweep_reason})"
            say(f"{device.idVendor:04x}:{device.idProduct:04x}  {info.manufacturer} "
                f"{info.model}  vendor={session.vendor}  focal stack: {stack}  sweep: {sweep}")
            found.append({"usb_id": f"{device.idVendor:04x}:{device.idProduct:04x}",
                          "manufacturer": info.manufacturer, "model": info.model,
                          "vendor": session.vendor, "stack": cap.stack, "sweep": cap.sweep,
                          "stack_reason": cap.stack_reason, "sweep_reason": cap.sweep_reason})
        finally:
            session.close()
    if args.json:
        print_json({"usb_devices": len(seen), "cameras": found})
    return 0


def _stack(args) -> int:
    from pipeline.tether.flows import StackPlan, capture_stack, connect

    plan = StackPlan(args.frames, args.step, args.direction, args.settle_ms / 1e3)
    lens, _profile = _lens(args)
    with connect(_backend(args), drive_size=args.drive_size, drive_pace_s=_pace(args)) as camera:
        result = capture_stack(camera, args.output, plan, lens=lens)
    if args.json:
        print_json({"output": str(args.output), "frames": len(result.frames)})
    else:
        print(f"{len(result.frames)} frames and stack.toml written to {args.output}")
    return 0


def _sweep(args) -> int:
    from pipeline.core.motion import constant_speed
    from pipeline.tether.flows import capture_sweep, connect, drive_schedule

    if args.steps < 1 or not (math.isfinite(args.exposure) and args.exposure > 0):
        raise InputError(f"--steps must be >= 1 and --exposure > 0 s, got {args.steps}, "
                         f"{args.exposure}")
    if args.fallback_step < 1 or args.period_ms <= 0:
        raise InputError("--fallback-step must be >= 1 and --period-ms > 0")
    lens_name, lens = _lens(args)
    step_um = lens.step_image_distance_um
    if step_um is None:
        log.info("%s has no calibrated step size; planning in steps (1 um per step)", lens_name)
        step_um = 1.0
    sign = 1 if args.direction == "near" else -1  # near focus lengthens p
    travel_mm = args.steps * step_um * 1e-3
    profile = constant_speed(lens.focal_length_mm + travel_mm, sign * travel_mm / args.exposure,
                             args.exposure)
    schedule = drive_schedule(profile, step_um * 1e-3, period_s=args.period_ms / 1e3)
    with connect(_backend(args, bulb=True), drive_size=args.drive_size,
                 drive_pace_s=_pace(args), bulb=True) as camera:
        result = capture_sweep(camera, args.output, schedule, args.exposure, lens=lens_name,
                               fallback_step=args.fallback_step)
    if args.json:
        print_json({"output": str(args.output), "fell_back": result.fell_back,
                    "drive_commands": len(result.drive_log), "message": result.message})
    elif result.fell_back:
        print(result.message)
    else:
        print(f"sweep of {args.steps} steps in {args.exposure} s written to {args.output} "
              f"({len(result.drive_log)} drive commands, times in drives.toml)")
    return 0


def _calibrate(args) -> int:
    from pipeline.io.profiles import lens_to_toml, load_lens
    from pipeline.tether.calibrate import calibrate_stack
    from pipeline.tether.flows import write_atomic

    lens = load_lens(args.lens)
    cal = calibrate_stack(args.stack, lens.focal_length_mm,
                          reference_focus_distance_mm=args.reference_focus_distance_mm)
    calibrated = dataclasses.replace(lens, step_image_distance_um=cal.step_image_distance_um)
    write_atomic(args.output, lens_to_toml(calibrated))
    if args.json:
        print_json({"output": str(args.output), "step_image_distance_um":
                    cal.step_image_distance_um, "rms_residual_um": cal.rms_residual_um,
                    "frames": len(cal.steps)})
        return 0
    print(f"{cal.step_image_distance_um:.4g} um of image distance per step "
          f"(rms residual {cal.rms_residual_um:.3g} um, {len(cal.steps)} frames); "
          f"written to {args.output}")
    return 0
