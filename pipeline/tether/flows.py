"""Capture flows: focal stack (drive, shoot, download) and focus-sweep (bulb + drive).

The camera is put back in a safe state (shutter closed, live view off, remote
mode off) and the session closed on every exit path, KeyboardInterrupt
included. Frames already downloaded stay on disk; a stack that ends early gets
``partial = true``. Every wait goes through the camera's clock.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.errors import InputError, TetherError
from pipeline.tether.base import DriveRefused, FocusCamera
from pipeline.tether.capabilities import body_capability
from pipeline.tether.clock import SYSTEM_CLOCK
from pipeline.tether.dispatch import camera_for
from pipeline.tether.session import CameraBusy, PtpSession, UnsupportedCamera
from pipeline.tether.transport import DeviceGone, UsbTransport, find_cameras, no_camera_message

if TYPE_CHECKING:
    from pipeline.core.motion import Profile

log = logging.getLogger(__name__)

DIRECTIONS = {"near": -1, "far": 1}


# --- stack.toml -------------------------------------------------------------------------------


def stack_toml_text(lens: str, frames: list[tuple[str, int]], *, partial: bool = False,
                    kind: str = "focal-stack") -> str:
    """The ``stack.toml`` of a captured stack: lens, kind, optional ``partial``, frames."""
    lines = [f"lens = {_quote(lens)}", f"kind = {_quote(kind)}"]
    if partial:
        lines.append("partial = true")
    for name, step in frames:
        lines += ["", "[[frames]]", f"file = {_quote(name)}", f"focus_step = {int(step)}"]
    return "\n".join(lines) + "\n"


def _quote(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def write_atomic(path: Path, data: bytes | str) -> None:
    """Write via a temporary file in the same directory and ``os.replace``.

    The file gets the mode a plain ``open()`` would give (0666 less the umask),
    not the 0600 of :func:`tempfile.mkstemp`.
    """
    blob = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
            os.fchmod(fh.fileno(), 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


# --- connecting -------------------------------------------------------------------------------


@contextlib.contextmanager
def connect(backend=None, *, drive_size: int = 1, drive_pace_s: float | None = None,
            clock=None, bulb: bool = False,
            known_operations=()) -> Iterator[FocusCamera]:
    """Open the first camera, check it can do the flow, yield its driver, always clean up.

    A body that :func:`~pipeline.tether.capabilities.body_capability` refuses for
    the flow (stack, or sweep with ``bulb``) raises :class:`UnsupportedCamera`
    with one line naming the body and what it lacks, right after the session
    opens: nothing is started or captured.

    Parameters
    ----------
    backend : usb.backend.IBackend, optional
        Default: libusb. An emulated backend brings its own (virtual) clock.
    drive_size, drive_pace_s
        Passed to the driver.
    clock : optional
        Default: the backend's ``clock`` attribute, else the system clock.
    bulb : bool
        The flow exposes in bulb while driving (a sweep): refuse bodies that cannot.
    known_operations : iterable of int
        Operations this body performs although GetDeviceInfo hides them (per-body table).
    """
    cameras, seen = find_cameras(backend)
    if not cameras:
        raise TetherError(no_camera_message(seen))
    if clock is None:
        clock = getattr(backend, "clock", SYSTEM_CLOCK)
    session = PtpSession(UsbTransport(cameras[0]), clock=clock)
    session.extra_operations |= set(known_operations)
    try:
        info = session.open()
        # the body table's decision on the camera's own GetDeviceInfo, before any capture
        refusal = body_capability(info, session.extra_operations).refusal(sweep=bulb)
        if refusal:
            raise UnsupportedCamera(refusal)
        camera = camera_for(session, drive_size=drive_size, drive_pace_s=drive_pace_s)
        camera.check_supported(bulb=bulb)
        try:
            camera.start()  # a start that fails half way must be undone too
            yield camera
        finally:
            camera.safe_state()
    finally:
        _close_quietly(session)


def _close_quietly(session: PtpSession) -> None:
    try:
        session.close()
    except TetherError as err:
        log.warning("could not close the PTP session: %s", err)


# --- focal stack ------------------------------------------------------------------------------


@dataclass(frozen=True)
class StackPlan:
    """``frames`` frames, ``step`` drive steps apart, towards ``direction``."""

    frames: int
    step: int
    direction: str = "far"
    settle_s: float = 0.2
    bulb_s: float | None = None  # expose each frame in bulb for this long (camera set to bulb)

    def __post_init__(self) -> None:
        if isinstance(self.frames, bool) or not isinstance(self.frames, int) or self.frames < 1:
            raise InputError(f"--frames must be an integer >= 1, got {self.frames!r}")
        if isinstance(self.step, bool) or not isinstance(self.step, int) or self.step < 1:
            raise InputError(f"--step must be an integer >= 1 (drive steps), got {self.step!r}")
        if self.direction not in DIRECTIONS:
            raise InputError(f"--direction must be near or far, got {self.direction!r}")
        if not (math.isfinite(self.settle_s) and self.settle_s >= 0):
            raise InputError(f"--settle-ms must be >= 0, got {self.settle_s * 1e3!r}")


@dataclass
class StackResult:
    directory: Path
    frames: list[tuple[str, int]] = field(default_factory=list)
    partial: bool = False


def capture_stack(camera: FocusCamera, out_dir: Path, plan: StackPlan, *, lens: str,
                  on_frame: Callable[[int, str, int], None] | None = None) -> StackResult:
    """Drive, shoot and download each frame; ``stack.toml`` after every frame.

    ``focus_step`` is the drive position (steps from the first frame, + = far).
    If the camera fails mid-way the frames downloaded so far stay and
    ``stack.toml`` says ``partial = true``; the error names how many were saved.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    result = StackResult(out_dir)
    toml = out_dir / "stack.toml"
    sign = DIRECTIONS[plan.direction]
    try:
        for index in range(plan.frames):
            if index:
                camera.drive(sign * plan.step)
                camera.settle(plan.settle_s)
            obj = camera.capture() if plan.bulb_s is None else camera.capture_bulb(plan.bulb_s)
            data = camera.download(obj)
            name = f"frame_{index:03d}{Path(obj.filename).suffix.lower()}"
            write_atomic(out_dir / name, data)
            result.frames.append((name, camera.position))
            write_atomic(toml, stack_toml_text(lens, result.frames,
                                               partial=index + 1 < plan.frames))
            if on_frame is not None:
                on_frame(index, name, camera.position)
    except (TetherError, KeyboardInterrupt) as err:
        result.partial = True
        write_atomic(toml, stack_toml_text(lens, result.frames, partial=True))
        if isinstance(err, KeyboardInterrupt):
            raise
        cause = "camera disconnected" if isinstance(err, DeviceGone) else "capture failed"
        raise type(err)(
            f"{cause} after {len(result.frames)} of {plan.frames} frames ({err}); the frames "
            f"already downloaded are in {out_dir} and stack.toml is marked partial"
        ) from err
    return result


# --- focus sweep ------------------------------------------------------------------------------


def drive_schedule(profile: Profile, step_mm: float, *, period_s: float) -> list[tuple[float, int]]:
    """(time s, signed steps) drive commands that follow ``profile`` every ``period_s``.

    The focus must be ``round((p(0) - p(t)) / step_mm)`` steps from its start at
    time ``t`` (+ = far, which shortens p; Sec. 8: moving the lens realises the
    planned detector motion p(t)); a command is issued whenever that count
    changes at a sampling instant.
    """
    if not (step_mm > 0 and period_s > 0):
        raise InputError(f"step_mm and period_s must be > 0, got {step_mm}, {period_s}")
    t0 = profile.times_s[0]
    times = np.arange(t0, profile.times_s[-1] + 1e-12, period_s)
    targets = np.round((profile.start_mm - profile.position(times)) / step_mm).astype(int)
    schedule, at = [], 0
    for t, target in zip(times, targets):
        if target != at:
            schedule.append((float(t - t0), int(target - at)))
            at = int(target)
    return schedule


@dataclass
class SweepResult:
    directory: Path
    fell_back: bool
    drive_log: list[tuple[float, int]]
    message: str = ""


def capture_sweep(camera: FocusCamera, out_dir: Path, schedule: list[tuple[float, int]],
                  exposure_s: float, *, lens: str, fallback_step: int) -> SweepResult:
    """One bulb exposure while driving the focus on ``schedule``; dense stack if refused.

    Writes ``capture.<ext>``, ``stack.toml`` (kind ``sweep``) and ``drives.toml``
    (each drive command's time from the shutter opening). If the camera refuses
    to drive while exposing, the exposure is closed and discarded, and a dense
    focal stack over the same range (``fallback_step`` apart, each frame exposed
    ``exposure_s`` in bulb) is captured instead.
    """
    total = sum(steps for _t, steps in schedule)
    commands = sum(camera.drive_commands(steps) for _t, steps in schedule)
    if commands * camera.drive_pace_s > exposure_s:
        raise InputError(
            f"the sweep needs {commands} drive commands at least {camera.drive_pace_s * 1e3:.0f} "
            f"ms apart ({commands * camera.drive_pace_s:.1f} s) but the exposure is "
            f"{exposure_s} s; use a longer --exposure, fewer --steps or a larger --drive-size"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    clock = camera.clock
    log_rows: list[tuple[float, int]] = []
    refused: TetherError | None = None
    camera.open_exposure()
    start = clock.now()
    try:
        try:
            for at_s, steps in schedule:
                clock.sleep(start + at_s - clock.now())
                issued = clock.now() - start
                camera.drive(steps)
                log_rows.append((issued, steps))
            clock.sleep(start + exposure_s - clock.now())
        except (DriveRefused, CameraBusy) as err:
            refused = err
        exposed_s = clock.now() - start
        obj = camera.close_exposure()
    finally:
        camera.abort_exposure()  # any other error or Ctrl-C: the shutter must not stay open
    write_atomic(out_dir / "drives.toml", "".join(
        f"[[drives]]\nt_s = {t:.6f}\nsteps = {s}\n\n" for t, s in log_rows))
    if refused is None:
        if exposed_s > 1.05 * exposure_s:
            log.warning("the drives ran late: the exposure lasted %.3g s instead of %.3g s",
                        exposed_s, exposure_s)
        name = f"capture{Path(obj.filename).suffix.lower()}"
        write_atomic(out_dir / name, camera.download(obj))
        # what the camera acknowledged and how long the shutter was really open
        write_atomic(out_dir / "stack.toml", _sweep_toml(lens, name, round(exposed_s, 6),
                                                          camera.position))
        return SweepResult(out_dir, False, log_rows)
    camera.download(obj)  # clear it from the camera; the exposure is not a sweep
    camera.drive(-camera.position)
    message = (
        f"camera refused to drive the focus while exposing ({refused}); "
        f"falling back to a dense focal stack of {total // fallback_step + 1} frames, "
        f"{fallback_step} steps apart"
    )
    log.warning(message)
    direction = "far" if total >= 0 else "near"
    plan = StackPlan(abs(total) // fallback_step + 1, fallback_step, direction,
                     bulb_s=exposure_s)
    capture_stack(camera, out_dir, plan, lens=lens)
    return SweepResult(out_dir, True, log_rows, message)


def _sweep_toml(lens: str, name: str, exposure_s: float, total_steps: int) -> str:
    return (
        f"lens = {_quote(lens)}\nkind = \"sweep\"\n\n[sweep]\nfile = {_quote(name)}\n"
        f"start_focus_step = 0\nend_focus_step = {total_steps}\nexposure_s = {exposure_s!r}\n"
        "profile = \"constant-speed\"\n"
    )
