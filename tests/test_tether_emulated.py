"""Real PTP code through real pyusb against the emulated camera backend."""

from __future__ import annotations

import dataclasses
import logging
import math
import struct
import tomllib
from pathlib import Path

import numpy as np
import pytest
import usb.core

from pipeline import cli
from pipeline.errors import InputError, TetherError
from pipeline.io.profiles import lens_to_toml, load_lens
from pipeline.io.read import read_frame
from pipeline.tether.base import CapturedObject, EndStop
from pipeline.tether.clock import VirtualClock
from pipeline.tether.codes import OC, RC, CanonOC, CanonRC, NikonOC
from pipeline.tether.emulated.device import (
    EmulatedBackend,
    EmulatedCamera,
    Faults,
    OtherDevice,
    StoredObject,
)
from pipeline.tether.emulated.personalities import CANON, EOS_SWEEP, NIKON
from pipeline.tether.emulated.scene import UM_PER_STEP
from pipeline.tether.flows import StackPlan, capture_stack, capture_sweep, connect
from pipeline.tether.ptp import ProtocolError
from pipeline.tether.session import CameraBusy, PtpError, PtpSession, UnsupportedCamera
from pipeline.tether.transport import (
    MAX_TRANSFER,
    DeviceGone,
    EndpointStalled,
    TransportTimeout,
    UsbTransport,
)


def _stack(cam, out, plan, **kw):
    with connect(EmulatedBackend(cam), **kw) as camera:
        return capture_stack(camera, out, plan, lens="sigma-30mm-f1.4-canon-eos-20d")


def _assert_safe(cam):
    assert not cam.evf_on and cam.remote_mode == 0 and not cam.live_view
    assert not cam.session_open


def test_pyusb_sees_the_emulator_as_a_still_image_device():
    dev = usb.core.find(backend=EmulatedBackend(EmulatedCamera(CANON)))
    intf = dev.get_active_configuration()[(0, 0)]
    assert (intf.bInterfaceClass, intf.bInterfaceSubClass, intf.bInterfaceProtocol) == (6, 1, 1)
    assert usb.util.get_string(dev, dev.iProduct) == "Canon EOS 60D (emulated)"


@pytest.mark.parametrize(("personality", "frames", "step", "direction"),
                         [(CANON, 20, 12, "far"), (NIKON, 8, 15, "near")])
def test_stack_steps_match_motor_log(tmp_path, personality, frames, step, direction):
    cam = EmulatedCamera(personality, position=0 if direction == "far" else 300)
    result = _stack(cam, tmp_path, StackPlan(frames, step, direction, 0.0))
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert meta["kind"] == "focal-stack" and "partial" not in meta
    assert len(meta["frames"]) == frames == len(cam.shots)
    start = cam.shots[0][1]
    units = personality.steps_per_size[1]
    for frame, (_handle, motor) in zip(meta["frames"], cam.shots):
        assert frame["focus_step"] * units == motor - start  # the emulator's motor position
        assert (tmp_path / frame["file"]).stat().st_size > 1000
    assert [m for _t, m in cam.motor_log][-1] == cam.shots[-1][1]
    tids = [t for t, op, _p in cam.transactions if op not in (OC.GetDeviceInfo, OC.OpenSession)]
    assert tids == list(range(1, len(tids) + 1))  # transaction ids count up in the session
    assert result.frames[-1][1] == (frames - 1) * step * (1 if direction == "far" else -1)
    _assert_safe(cam)


def test_downloads_with_zlp_on_both_directions(tmp_path):
    cam = EmulatedCamera(CANON)
    payload = bytes(range(256)) * ((MAX_TRANSFER + 500) // 256 + 10)
    cam.objects[99] = StoredObject("BIG.JPG", payload, 0x3801)
    with connect(EmulatedBackend(cam)) as camera:
        # data container of MAX_TRANSFER + 512 bytes: a full first read, then one packet + ZLP
        obj = CapturedObject(99, len(payload), "BIG.JPG")
        assert camera.download(obj, chunk=MAX_TRANSFER + 500) == payload
        assert camera.session.transport._pending == b""
        # host-to-device data phase of exactly one packet (12 + 500 bytes) must end with a ZLP
        before = cam.zlps_received
        camera.session.transaction(CanonOC.SetDevicePropValueEx,
                                   data_out=struct.pack("<III", 500, 0xD1B3, 0) + bytes(488))
        assert cam.zlps_received == before + 1


def test_busy_responses_are_retried(tmp_path):
    cam = EmulatedCamera(CANON, faults=Faults(busy_responses=6))
    with connect(EmulatedBackend(cam)) as camera:
        capture_stack(camera, tmp_path, StackPlan(4, 3, settle_s=0.0), lens="l")
        assert camera.session.retried == 6
    assert cam.busy_given == 6 and len(cam.shots) == 4


def test_end_stop_is_reported_and_camera_made_safe(tmp_path):
    cam = EmulatedCamera(NIKON, position=380, limits=(0, 400))
    with pytest.raises(EndStop, match="far end stop"):
        _stack(cam, tmp_path, StackPlan(6, 10, "far", 0.0))
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert meta["partial"] is True and len(meta["frames"]) == 3
    _assert_safe(cam)


def test_unplug_mid_stack_keeps_downloaded_frames(tmp_path):
    cam = EmulatedCamera(CANON, faults=Faults(unplug_on_download=3))
    with pytest.raises(DeviceGone, match=r"camera disconnected after 3 of 10 frames"):
        _stack(cam, tmp_path, StackPlan(10, 5, settle_s=0.0))
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert meta["partial"] is True
    assert [f["file"] for f in meta["frames"]] == [f"frame_{i:03d}.jpg" for i in range(3)]
    assert all((tmp_path / f["file"]).is_file() for f in meta["frames"])
    assert not (tmp_path / "frame_003.jpg").exists()


def test_timeout_cancels_and_session_stays_usable():
    cam = EmulatedCamera(CANON)
    with connect(EmulatedBackend(cam)) as camera:
        cam.faults.timeout_on = CanonOC.DriveLens
        with pytest.raises(TransportTimeout, match="cancelled"):
            camera.drive(1)
        hung = [t for t, op, _p in cam.transactions if op == CanonOC.DriveLens][-1]
        assert cam.cancelled == [hung]  # class request 0x64 named the hung transaction
        camera.drive(2)
        assert cam.position == 2
        cam.faults.stall_on = CanonOC.GetEvent
        with pytest.raises(EndpointStalled):
            camera.poll_events()
        assert 0x81 in cam.halts_cleared
        assert camera.capture().size > 0
    _assert_safe(cam)


def test_keyboard_interrupt_restores_camera(tmp_path):
    cam = EmulatedCamera(CANON)

    def interrupt(index, _name, _step):
        if index == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt), connect(EmulatedBackend(cam)) as camera:
        assert cam.evf_on and cam.remote_mode == 1
        capture_stack(camera, tmp_path, StackPlan(8, 2, settle_s=0.0), lens="l",
                      on_frame=interrupt)
    _assert_safe(cam)
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert meta["partial"] is True and len(meta["frames"]) == 3


def test_sweep_drives_during_bulb_when_allowed(tmp_path):
    cam = EmulatedCamera(EOS_SWEEP, shutter="bulb")
    schedule = [(0.5 * i, 5) for i in range(1, 6)]
    with connect(EmulatedBackend(cam), bulb=True) as camera:
        result = capture_sweep(camera, tmp_path, schedule, 3.0, lens="l", fallback_step=5)
    assert not result.fell_back and len(cam.shots) == 1
    assert cam.shots[0][1] == 25 * EOS_SWEEP.steps_per_size[1]
    drives = tomllib.loads((tmp_path / "drives.toml").read_text())["drives"]
    times = [d["t_s"] for d in drives]
    assert [d["steps"] for d in drives] == [5] * 5
    assert times == sorted(times) and all(t >= s for t, (s, _n) in zip(times, schedule))
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert meta["kind"] == "sweep" and (tmp_path / meta["sweep"]["file"]).is_file()
    assert cam.dropped_drives == 0
    _assert_safe(cam)


def test_sweep_falls_back_to_dense_stack_when_refused(tmp_path, capsys):
    rc = cli.main(["tether", "sweep", "-o", str(tmp_path), "--steps", "40", "--exposure", "5",
                   "--emulate", "canon", "--fallback-step", "10"])
    assert rc == 0
    assert "falling back to a dense focal stack of 5 frames" in capsys.readouterr().out
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert [f["focus_step"] for f in meta["frames"]] == [0, 10, 20, 30, 40]


def test_no_camera_lists_what_was_seen():
    with pytest.raises(TetherError, match=r"no PTP camera.*1d6b:0002 \(unknown vendor, class 9\)"):
        with connect(EmulatedBackend(OtherDevice())):
            pass


def test_unsupported_camera_names_missing_operations():
    ops = tuple(op for op in CANON.operations if op != CanonOC.DriveLens)
    cam = EmulatedCamera(CANON.but(operations=ops, model="Old EOS"))
    with pytest.raises(UnsupportedCamera, match=r"^Old EOS cannot capture a focal stack: no live "
                                                r"view or DriveLens in GetDeviceInfo \(lacks "
                                                r"DriveLens \(0x9155\)\)$"):
        with connect(EmulatedBackend(cam)):
            pass
    assert not cam.session_open


@pytest.mark.parametrize(("frames", "step", "match"),
                         [(0, 5, "--frames"), (5, 0, "--step"), (5, -3, "--step")])
def test_invalid_plan(frames, step, match):
    with pytest.raises(InputError, match=match):
        StackPlan(frames, step)


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert cli.main(["tether", "stack", "-o", str(tmp_path), "--frames", "3", "--step", "0",
                     "--emulate", "canon"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--step must be an integer >= 1" in err
    assert cli.main(["tether", "stack", "-o", str(tmp_path), "--frames", "3", "--step", "2",
                     "--emulate", "nikon", "--drive-size", "2"]) == 2
    assert "Nikon MfDrive has no step sizes" in capsys.readouterr().err


def test_calibration_recovers_emulator_step_size(tmp_path):
    stack, profile = tmp_path / "stack", tmp_path / "lens.toml"
    assert cli.main(["tether", "stack", "-o", str(stack), "--frames", "12", "--step", "20",
                     "--emulate", "canon", "--settle-ms", "0"]) == 0
    # the emulator's step 0 focuses 600 mm (+0.1 mm), so the reference p is ~ f u / (u - f)
    assert cli.main(["tether", "calibrate", str(stack), "--lens", "sigma-30mm-f1.4-canon-eos-20d",
                     "-o", str(profile), "--reference-focus-distance-mm", "600"]) == 0
    lens = load_lens(profile)
    assert math.isclose(lens.step_image_distance_um, UM_PER_STEP, rel_tol=0.05)
    assert lens.focal_length_mm == 30.0


def _gradient_energy(image) -> float:
    grey = image.mean(axis=-1) if image.ndim == 3 else image
    return float(np.mean(np.diff(grey, axis=0) ** 2) + np.mean(np.diff(grey, axis=1) ** 2))


def _assert_sharper_than_the_plain_average(out: Path, stack: Path) -> None:
    """The result is an image of the frames' scene, sharper than their plain average."""
    result = read_frame(out)
    frames = [read_frame(p) for p in sorted(stack.iterdir()) if p.suffix.lower() in FRAME_EXT]
    assert frames and result.shape == frames[0].shape
    average = np.mean(frames, axis=0)
    assert abs(float(result.mean()) - float(average.mean())) < 0.05 * float(average.mean())
    assert _gradient_energy(result) > 1.5 * _gradient_energy(average)


FRAME_EXT = {".jpg", ".jpeg", ".tif", ".tiff", ".png", ".cr2", ".nef"}


def test_emulated_stack_processes_to_edof(tmp_path: Path):
    """Capture with the emulator, then run the lead's ``flexdof stack`` on it."""
    stack, out = tmp_path / "stack", tmp_path / "edof.tif"
    assert cli.main(["tether", "stack", "-o", str(stack), "--frames", "20", "--step", "12",
                     "--emulate", "canon", "--settle-ms", "0"]) == 0
    assert cli.main(["stack", str(stack), "-o", str(out)]) == 0
    _assert_sharper_than_the_plain_average(out, stack)


def test_nikon_step_too_small_is_an_input_error():
    cam = EmulatedCamera(NIKON)
    with connect(EmulatedBackend(cam)) as camera:
        with pytest.raises(InputError, match="too small"):
            camera._drive(0)  # amount 0: MfDriveStepInsufficiency from DeviceReady
    assert NikonOC.MfDrive in {op for _t, op, _p in cam.transactions}


def test_device_reset_closes_the_session_and_it_can_reopen():
    cam = EmulatedCamera(NIKON)
    with connect(EmulatedBackend(cam)) as camera:
        transport = camera.session.transport
        assert transport.device_status() == (0x2001, ())  # Get Device Status 0x67: OK
        transport.reset()  # Device Reset 0x66
        assert not cam.session_open
        camera.session.is_open = False
        camera.session.open()
        assert cam.session_open
        camera.start()
    _assert_safe(cam)


def test_tethered_sweep_processes_with_a_calibrated_lens(tmp_path, capsys):
    """A sweep capture's stack.toml (focus steps) deconvolves once the lens is calibrated."""
    cam = EmulatedCamera(EOS_SWEEP, shutter="bulb")
    schedule = [(0.5 * i, 5) for i in range(1, 6)]
    shots = tmp_path / "sweep"
    shots.mkdir()
    with connect(EmulatedBackend(cam), bulb=True) as camera:
        capture_sweep(camera, shots, schedule, 3.0, lens="sigma-30mm-f1.4-canon-eos-20d",
                      fallback_step=5)
    out = tmp_path / "edof.tif"
    # the shipped profile has no step calibration: a clear error, nothing written
    assert cli.main(["stack", str(shots), "-o", str(out)]) == 2
    assert "calibrate" in capsys.readouterr().err and not out.exists()
    calibrated = tmp_path / "lens.toml"
    lens = load_lens("sigma-30mm-f1.4-canon-eos-20d")
    calibrated.write_text(lens_to_toml(dataclasses.replace(lens, step_image_distance_um=5.0)))
    assert cli.main(["-q", "stack", str(shots), "-o", str(out), "--lens", str(calibrated)]) == 0
    _assert_sharper_than_the_plain_average(out, shots)  # the sweep image, deconvolved


def test_tether_commands_speak_the_cli_vocabulary(tmp_path, capsys):
    """--json on every tether action, --exposure-s like the other commands."""
    import json

    from pipeline.cli import main

    assert main(["tether", "stack", "--emulate", "canon", "-o", str(tmp_path / "s"),
                 "--frames", "3", "--step", "10", "--settle-ms", "0", "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"output": str(tmp_path / "s"), "frames": 3}
    assert main(["tether", "sweep", "--emulate", "canon", "--personality", "eos-sweep",
                 "-o", str(tmp_path / "w"), "--steps", "40", "--exposure-s", "5", "--json"]) == 0
    sweep = json.loads(capsys.readouterr().out)
    assert sweep["fell_back"] is False and sweep["drive_commands"] == 40
    assert main(["tether", "list", "--emulate", "nikon", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [c["vendor"] for c in listed["cameras"]] == ["nikon"]
    assert listed["cameras"][0]["stack"] is True and listed["cameras"][0]["sweep"] is False


# --- PtpSession on its own, over pyusb and the emulator ----------------------------------------


def _raw_session(cam, **options) -> PtpSession:
    backend = EmulatedBackend(cam)
    return PtpSession(UsbTransport(usb.core.find(backend=backend)), clock=backend.clock,
                      **options)


def _ops(cam) -> list[tuple[int, int]]:
    return [(tid, op) for tid, op, _params in cam.transactions]


def test_open_closes_a_stale_session_and_transaction_ids_restart():
    cam = EmulatedCamera(CANON)
    cam.session_open = True  # left open by a host that died
    session = _raw_session(cam)
    info = session.open()
    assert (info.model, session.vendor, session.is_open) == (CANON.model, "canon", True)
    # outside a session GetDeviceInfo and OpenSession use transaction id 0 (ISO 15740 9.3.1)
    assert _ops(cam) == [(0, OC.GetDeviceInfo), (0, OC.OpenSession), (1, OC.CloseSession),
                         (0, OC.OpenSession)]
    session.transaction(OC.GetDeviceInfo, want_data=True)
    session.transaction(OC.GetDeviceInfo, want_data=True)
    assert _ops(cam)[4:] == [(1, OC.GetDeviceInfo), (2, OC.GetDeviceInfo)]
    session._tid = 0xFFFFFFFD  # ids run 1 .. 0xFFFFFFFE; 0xFFFFFFFF is reserved
    session.transaction(OC.GetDeviceInfo, want_data=True)
    session.transaction(OC.GetDeviceInfo, want_data=True)
    assert [tid for tid, _op in _ops(cam)[6:]] == [0xFFFFFFFE, 1]
    session.close()
    assert not cam.session_open and _ops(cam)[-1] == (2, OC.CloseSession)
    session.close()  # twice: no second CloseSession
    assert len(cam.transactions) == 9


def test_session_vendor_comes_from_the_extension_id_before_the_usb_vendor():
    # a Canon USB id (0x04A9) with Nikon's PTP extension id (0xA): the extension id decides
    session = _raw_session(EmulatedCamera(CANON.but(vendor_extension_id=0xA)))
    session.open()
    assert session.vendor == "nikon"
    session = _raw_session(EmulatedCamera(CANON))  # extension id 6 (MTP): the USB id decides
    session.open()
    assert session.vendor == "canon"


def test_supports_and_require_name_what_is_missing():
    ops = tuple(op for op in CANON.operations if op not in (CanonOC.DriveLens, CanonOC.GetEvent))
    session = _raw_session(EmulatedCamera(CANON.but(operations=ops, model="Old EOS")))
    assert not session.supports(OC.GetDeviceInfo)  # nothing known before GetDeviceInfo
    session.open()
    assert session.supports(OC.GetDeviceInfo) and not session.supports(CanonOC.DriveLens)
    with pytest.raises(UnsupportedCamera, match=r"^Old EOS cannot focus: it lacks DriveLens "
                                                r"\(0x9155\), GetEvent \(0x9116\)$"):
        session.require([OC.GetDeviceInfo, CanonOC.DriveLens, CanonOC.GetEvent], "focus")
    session.extra_operations |= {CanonOC.DriveLens, CanonOC.GetEvent}
    session.require([CanonOC.DriveLens, CanonOC.GetEvent], "focus")  # hidden but known
    assert session.supports(CanonOC.DriveLens)
    session.require([], "do nothing")


def test_failures_raise_with_the_response_and_busy_can_be_returned_at_once():
    cam = EmulatedCamera(CANON, faults=Faults(busy_responses=1))
    session = _raw_session(cam)
    session.open()
    cam.faults.busy_ops = frozenset({CanonOC.SetRemoteMode})
    response = session.transaction(CanonOC.SetRemoteMode, (1,), check=False, busy_ok=False)
    assert response.code == RC.DeviceBusy and session.retried == 0  # no retry, no wait
    cam.faults.error_on[CanonOC.SetRemoteMode] = RC.GeneralError
    with pytest.raises(PtpError, match=r"^SetRemoteMode \(0x9114\) failed: GeneralError "
                                       r"\(0x2002\)$") as err:
        session.transaction(CanonOC.SetRemoteMode, (1,))
    assert err.type is PtpError and err.value.code == RC.GeneralError
    cam.faults.busy_responses = 3
    with pytest.raises(CameraBusy, match=r"DeviceBusy \(0x2019\) after 2 retries$") as err:
        _raw_session(cam, retries=2).transaction(CanonOC.SetRemoteMode, (1,))
    assert err.value.code == RC.DeviceBusy


# --- mutation kills (tether/session.py) -------------------------------------------------------


class _SleepLog(VirtualClock):
    """A virtual clock that keeps every wait the host asks for."""

    def __init__(self) -> None:
        super().__init__()
        self.sleeps: list[float] = []

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(round(seconds, 9))
        super().sleep(seconds)


class _SlowCancel(EmulatedCamera):
    """A body that reports DeviceBusy to ``busy_polls`` device-status requests after a cancel
    (the still-image class lets a device take its time to abort a transaction)."""

    busy_polls = 0

    def class_request(self, request, data, length):
        if request == 0x67 and self.busy_polls and self._hanging is None:
            self.busy_polls -= 1
            return struct.pack("<HH", 4, RC.DeviceBusy)
        return super().class_request(request, data, length)


class _Garbled(EmulatedCamera):
    """A body that answers with another transaction's id (``shift_tid``), sends its data
    phase twice (``repeat_data``) or an empty container of type ``insert_kind`` before the
    response, once each."""

    shift_tid = 0
    repeat_data = False
    insert_kind = None

    def _queue(self, blob):
        kind, tid = struct.unpack_from("<H", blob, 4)[0], struct.unpack_from("<I", blob, 8)[0]
        if kind == 3 and self.insert_kind is not None:
            super()._queue(struct.pack("<IHHI", 12, self.insert_kind, 0x1003, tid))
            self.insert_kind = None
        if kind == 3 and self.shift_tid:
            blob = blob[:8] + struct.pack("<I", tid + self.shift_tid) + blob[12:]
            self.shift_tid = 0
        super()._queue(blob)
        if kind == 2 and self.repeat_data:
            self.repeat_data = False
            super()._queue(blob)


def test_a_slow_cancel_is_polled_with_doubling_waits_until_idle():
    clock = _SleepLog()
    cam = _SlowCancel(CANON, clock=clock)
    session = _raw_session(cam, retries=3, backoff_s=0.05, max_backoff_s=0.15)
    session.open()
    cam.faults.timeout_on, cam.busy_polls = OC.GetDeviceInfo, 3  # idle at the 4th = last poll
    with pytest.raises(TransportTimeout, match="cancelled"):
        session.transaction(OC.GetDeviceInfo, want_data=True)
    assert clock.sleeps == [0.05, 0.1, 0.15]  # doubled, capped at max_backoff_s
    assert cam.cancelled == [1] and cam.busy_polls == 0
    assert session.transaction(OC.GetDeviceInfo, want_data=True).code == RC.OK  # still usable
    clock.sleeps.clear()
    cam.faults.timeout_on, cam.busy_polls = OC.GetDeviceInfo, 4  # busy through every poll
    with pytest.raises(TetherError, match=r"^camera stayed DeviceBusy \(0x2019\) after "
                                          r"cancelling transaction 3; reset it") as err:
        session.transaction(OC.GetDeviceInfo, want_data=True)
    assert err.type is TetherError and clock.sleeps == [0.05, 0.1, 0.15, 0.15]


def _garbled(**fault) -> tuple[_Garbled, PtpSession]:
    cam = _Garbled(CANON)
    session = _raw_session(cam)
    session.open()
    for name, value in fault.items():
        setattr(cam, name, value)
    return cam, session


def test_a_response_to_another_transaction_or_a_second_data_phase_is_a_protocol_error():
    for shift, got in ((1, 2), (-1, 0)):
        _cam, session = _garbled(shift_tid=shift)
        with pytest.raises(ProtocolError, match=r"^GetDeviceInfo \(0x1001\): expected the "
                           rf"response to transaction 1, got a RESPONSE container for "
                           rf"transaction {got}$"):
            session.transaction(OC.GetDeviceInfo, want_data=True)
    _cam, session = _garbled(repeat_data=True)
    with pytest.raises(ProtocolError, match=r"expected the response to transaction 1, got a "
                                            r"DATA container for transaction 1$"):
        session.transaction(OC.GetDeviceInfo, want_data=True)
    # a command or an event container where the response of an operation without data
    # belongs (neither is a data phase nor a response)
    for kind, name in ((1, "COMMAND"), (4, "EVENT")):
        _cam, session = _garbled(insert_kind=kind)
        with pytest.raises(ProtocolError, match=rf"^SetRemoteMode \(0x9114\): expected the "
                           rf"response to transaction 1, got a {name} container for "
                           rf"transaction 1$"):
            session.transaction(CanonOC.SetRemoteMode, (1,))


def test_unexpected_data_is_logged_and_expected_data_is_not(caplog):
    cam = EmulatedCamera(CANON)
    session = _raw_session(cam)
    with caplog.at_level(logging.DEBUG, logger="pipeline.tether.session"):
        session.open()
        session.transaction(OC.GetDeviceInfo, want_data=True)
        session.transaction(OC.OpenSession, (1,), check=False)  # no data phase at all
        assert "unexpected" not in caplog.text
        response = session.transaction(OC.GetDeviceInfo)
    assert response.data == cam.device_info()  # kept all the same
    assert caplog.text.count(f"sent {len(response.data)} unexpected data bytes") == 1


def test_transaction_ids_of_a_new_session_object_start_at_1():
    cam = EmulatedCamera(CANON)
    session = _raw_session(cam)
    response = session.transaction(OC.CloseSession, check=False)  # before any OpenSession
    assert response.code == RC.SessionNotOpen and _ops(cam) == [(1, OC.CloseSession)]


def test_open_refused_with_another_code_is_an_error_without_a_close():
    """Only SessionAlreadyOpened closes and reopens; any other refusal (a vendor code
    sorting after it here) is raised at once. A response code below OK is no OK."""

    class _Refuses(EmulatedCamera):
        refusal = CanonRC.LowBattery

        def _operate(self, op, args, data_out):
            if op == OC.OpenSession and self.refusal is not None:
                return self.refusal, (), None
            return super()._operate(op, args, data_out)

    cam = _Refuses(CANON)
    session = _raw_session(cam)
    with pytest.raises(PtpError, match=r"^OpenSession \(0x1002\) failed: LowBattery "
                                       r"\(0xA101\)$") as err:
        session.open()
    assert err.value.code == CanonRC.LowBattery and not session.is_open
    assert _ops(cam) == [(0, OC.GetDeviceInfo), (0, OC.OpenSession)]
    cam.refusal = 0x2000  # "Undefined": not OK
    with pytest.raises(PtpError, match=r"^OpenSession \(0x1002\) failed: 0x2000$"):
        _raw_session(cam).open()


def test_a_response_is_an_immutable_value():
    session = _raw_session(EmulatedCamera(CANON))
    response = session.transaction(OC.GetDeviceInfo, want_data=True)
    with pytest.raises(dataclasses.FrozenInstanceError):
        response.code = RC.GeneralError
