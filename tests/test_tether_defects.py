"""Issue 12: one test (or more) per defect, against the strict emulator (``dN`` = defect N).

Each test fails when its fix is reverted (see the issue's list). Waits run on the
emulator's virtual clock, so bodies that stay busy for seconds cost no real time.
"""

from __future__ import annotations

import os
import struct
import tomllib

import pytest

from pipeline import cli
from pipeline.errors import InputError, TetherError
from pipeline.tether.base import CapturedObject, LensAtManual
from pipeline.tether.clock import VirtualClock
from pipeline.tether.codes import OC, CanonOC, NikonOC
from pipeline.tether.emulated.device import (
    EmulatedBackend,
    EmulatedCamera,
    Faults,
    StoredObject,
)
from pipeline.tether.emulated.personalities import CANON, EOS_M, EOS_R, EOS_SWEEP, NIKON
from pipeline.tether.flows import StackPlan, capture_stack, capture_sweep, connect
from pipeline.tether.session import UnsupportedCamera
from pipeline.tether.transport import DeviceGone

LENS = "sigma-30mm-f1.4-canon-eos-20d"


def _stack(cam, out, plan, **kw):
    with connect(EmulatedBackend(cam), **kw) as camera:
        return capture_stack(camera, out, plan, lens=LENS)


def _ops(cam, opcode):
    return [params for _tid, op, params in cam.transactions if op == opcode]


def _assert_safe(cam):
    assert not cam.exposing
    assert not cam.evf_on and cam.remote_mode == 0 and not cam.live_view
    assert not cam.session_open


def _shots_match_focus_steps(cam, result, units=1):
    start = cam.shots[0][1]
    return [pos - start for _h, pos in cam.shots] == [s * units for _n, s in result.frames]


# --- 1: Canon autofocuses every frame ---------------------------------------------------------


@pytest.mark.parametrize("af_succeeds", [True, False])
def test_d1_canon_release_does_not_autofocus(tmp_path, af_succeeds):
    cam = EmulatedCamera(CANON, af_target=250, faults=Faults(af_succeeds=af_succeeds))
    result = _stack(cam, tmp_path, StackPlan(4, 10, settle_s=0.0))
    assert len(cam.shots) == 4 and cam.af_refocused == 0 and cam.af_failures == 0
    assert [pos for _h, pos in cam.shots] == [0, 10, 20, 30]  # AF would have put them at 250
    assert _shots_match_focus_steps(cam, result)
    assert set(_ops(cam, CanonOC.RemoteReleaseOn)) == {(3, 1)}  # full press, MF (no AF)


def test_d1_lens_switch_at_mf_is_reported(tmp_path):
    cam = EmulatedCamera(CANON.but(focus_mode=3))
    with pytest.raises(LensAtManual, match=r"focus switch is at MF.*set the switch to AF"):
        _stack(cam, tmp_path, StackPlan(3, 5))
    assert not _ops(cam, CanonOC.DriveLens) and not cam.shots
    _assert_safe(cam)


# --- 2: a bulb sweep leaves the shutter open -----------------------------------------------


class InterruptingClock(VirtualClock):
    """Ctrl-C at a given virtual time (inside the host's waits)."""

    def __init__(self, at: float) -> None:
        super().__init__()
        self.at = at

    def sleep(self, seconds: float) -> None:
        super().sleep(seconds)
        if self.at is not None and self.t >= self.at:
            self.at = None
            raise KeyboardInterrupt


@pytest.mark.parametrize("fault", ["general-error", "ctrl-c"])
def test_d2_sweep_closes_the_shutter_on_every_error(tmp_path, fault):
    clock = InterruptingClock(1.0 if fault == "ctrl-c" else None)
    faults = Faults(error_on={CanonOC.DriveLens: 0x2002} if fault == "general-error" else {})
    cam = EmulatedCamera(EOS_SWEEP, shutter="bulb", clock=clock, faults=faults)
    schedule = [(0.3 * i, 2) for i in range(1, 8)]
    expected = KeyboardInterrupt if fault == "ctrl-c" else TetherError
    with pytest.raises(expected), connect(EmulatedBackend(cam), bulb=True) as camera:
        capture_sweep(camera, tmp_path, schedule, 3.0, lens=LENS, fallback_step=5)
    assert _ops(cam, CanonOC.RemoteReleaseOff)  # the exposure was ended
    _assert_safe(cam)


# --- 3: Nikon live view is not restarted after a capture -------------------------------------


@pytest.mark.parametrize(("personality", "starts"), [
    (NIKON, 4),  # at start, then after each capture but the last
    (NIKON.but(operations=tuple(op for op in NIKON.operations if op != OC.GetDevicePropValue)),
     4),  # no LiveViewStatus to ask: restart after every capture
    (NIKON.but(drops_live_view=False), 1),  # a body that keeps live view: no restart
])
def test_d3_nikon_live_view_restarted_after_each_capture(tmp_path, personality, starts):
    cam = EmulatedCamera(personality)
    result = _stack(cam, tmp_path, StackPlan(4, 15, settle_s=0.0))
    assert len(result.frames) == 4 and _shots_match_focus_steps(cam, result)
    assert len(_ops(cam, NikonOC.StartLiveView)) == starts
    _assert_safe(cam)


# --- 4: Nikon DeviceReady gives up after ~4.5 s and only knows 0x2019 --------------------------


@pytest.mark.parametrize("busy_code", [0x2019, 0xA200])
def test_d4_nikon_device_ready_waits_through_a_long_busy_body(tmp_path, busy_code):
    cam = EmulatedCamera(NIKON.but(ready_busy_s=25.0), faults=Faults(ready_busy_code=busy_code))
    result = _stack(cam, tmp_path, StackPlan(2, 10, settle_s=0.0))
    assert len(result.frames) == 2
    assert cam.clock.now() > 50.0  # two captures, each busy for 25 s of (virtual) time
    assert cam.busy_given > 100


# --- 5: the Nikon sweep cannot work as written ----------------------------------------------


def test_d5_nikon_sweep_is_refused_before_live_view(tmp_path):
    cam = EmulatedCamera(NIKON, shutter="bulb")
    with pytest.raises(UnsupportedCamera, match=r"^Nikon D5100 \(emulated\) cannot run a focus "
                                                r"sweep: Nikon: sweep not supported \(live view "
                                                r"is prohibited in bulb; no bulb path\); capture a "
                                                r"focal stack \(tether stack\) instead$"):
        with connect(EmulatedBackend(cam), bulb=True) as camera:
            capture_sweep(camera, tmp_path, [(0.1, 5)], 1.0, lens=LENS, fallback_step=5)
    assert not _ops(cam, NikonOC.StartLiveView) and not cam.shots
    assert not cam.session_open


def test_d5_cli_sweep_on_nikon_is_one_clear_line(tmp_path, capsys):
    assert cli.main(["tether", "sweep", "-o", str(tmp_path), "--steps", "20", "--exposure", "2",
                     "--emulate", "nikon"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "bulb" in err and "tether stack" in err


def test_d5_canon_sweep_personality_runs_the_real_sweep_path(tmp_path, capsys):
    assert cli.main(["tether", "sweep", "-o", str(tmp_path), "--steps", "30", "--exposure", "4",
                     "--emulate", "canon", "--personality", "eos-sweep"]) == 0
    assert "sweep of 30 steps" in capsys.readouterr().out
    drives = tomllib.loads((tmp_path / "drives.toml").read_text())["drives"]
    assert sum(d["steps"] for d in drives) == 30
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert meta["kind"] == "sweep" and meta["sweep"]["end_focus_step"] == 30


# --- 6: Canon images can be missed ----------------------------------------------------------


@pytest.mark.parametrize(("personality", "transfer"), [
    (CANON, False),  # card: folder object first, ObjectAddedEx, no TransferComplete
    (EOS_R, False),  # EOS R era: ObjectAddedEx64 (0xC1A7)
    (CANON.but(capture_destination=4), True),  # PC: RequestObjectTransfer (0xC186)
])
def test_d6_canon_images_are_found_however_announced(tmp_path, personality, transfer):
    cam = EmulatedCamera(personality)
    result = _stack(cam, tmp_path, StackPlan(3, 5, settle_s=0.0))
    assert len(result.frames) == 3
    for name, _step in result.frames:
        assert (tmp_path / name).read_bytes()[:2] == b"\xff\xd8"  # a JPEG, not the folder
    assert len(_ops(cam, CanonOC.TransferComplete)) == (3 if transfer else 0)
    assert cam.sdram == []  # nothing left held for the host


# --- 7: DriveLens back to back, no event poll -----------------------------------------------


@pytest.mark.parametrize("overlap", ["drop", "busy"])
def test_d7_drives_are_paced_polled_and_counted(tmp_path, overlap):
    cam = EmulatedCamera(CANON.but(drive_overlap=overlap))
    result = _stack(cam, tmp_path, StackPlan(4, 6, settle_s=0.0))
    assert cam.dropped_drives == 0
    assert _shots_match_focus_steps(cam, result)  # focus_step is where the motor really was
    ops = [op for _t, op, _p in cam.transactions]
    for i, op in enumerate(ops):
        if op == CanonOC.DriveLens:
            assert ops[i + 1] == CanonOC.GetEvent  # an event poll after every drive


def test_d7_frame_not_recorded_when_the_lens_switch_went_to_mf(tmp_path):
    cam = EmulatedCamera(CANON)

    def flip(index, _name, _step):
        if index == 1:
            cam.set_lens_switch("MF")  # later drives are ignored by the body

    with pytest.raises(LensAtManual), connect(EmulatedBackend(cam)) as camera:
        capture_stack(camera, tmp_path, StackPlan(5, 10, settle_s=0.0), lens=LENS,
                      on_frame=flip)
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    assert meta["partial"] is True and [f["focus_step"] for f in meta["frames"]] == [0, 10]
    assert len(cam.shots) == 2


def test_d7_capture_drains_unasked_events_first():
    cam = EmulatedCamera(CANON.but(chatter_s=0.5))
    with connect(EmulatedBackend(cam)) as camera:
        for _ in range(3):
            camera.clock.sleep(2.0)  # the body reports a property change meanwhile
            camera.download(camera.capture())
    assert len(cam.shots) == 3 and camera.session.retried == 0


def test_d7_sweep_that_cannot_be_paced_is_refused(tmp_path):
    cam = EmulatedCamera(EOS_SWEEP, shutter="bulb")
    with pytest.raises(InputError, match="drive commands at least 100 ms apart"):
        with connect(EmulatedBackend(cam), bulb=True) as camera:
            capture_sweep(camera, tmp_path, [(0.01, 40)], 1.0, lens=LENS, fallback_step=5)
    assert not cam.shots


# --- 8: Canon live view without EVFMode; EOS M ------------------------------------------------


@pytest.mark.parametrize("personality", [CANON.but(evf_mode=0), EOS_M])
def test_d8_live_view_sets_evf_mode_and_the_body_remote_mode(tmp_path, personality):
    cam = EmulatedCamera(personality)
    with connect(EmulatedBackend(cam)) as camera:
        assert cam.evf_on and cam.remote_mode == personality.remote_mode
        camera.drive(3)
        assert cam.position == 3
    _assert_safe(cam)


# --- 9: transport: container on a packet boundary without a ZLP -----------------------------


@pytest.mark.parametrize(("omit_zlp", "stray_zlp"), [(True, False), (False, True)])
def test_d9_containers_on_packet_boundaries(omit_zlp, stray_zlp):
    cam = EmulatedCamera(CANON.but(omit_zlp=omit_zlp), faults=Faults(stray_zlp=stray_zlp))
    payload = bytes(i % 251 for i in range(4096))
    with connect(EmulatedBackend(cam)) as camera:
        for size in (500, 1012, 2036, 1000):  # 12 + size: 512, 1024, 2048 bytes; 1012
            cam.objects[7] = StoredObject("X.JPG", payload[:size], 0x3801)
            obj = CapturedObject(7, size, "X.JPG")
            assert camera.download(obj) == payload[:size]
        assert camera.session.transport._pending == b""


# --- 10: smaller ------------------------------------------------------------------------------


def test_d10_image_wait_covers_long_noise_reduction(tmp_path):
    cam = EmulatedCamera(CANON.but(image_delay_s=30.0))
    result = _stack(cam, tmp_path, StackPlan(2, 5, settle_s=0.0))
    assert len(result.frames) == 2 and cam.clock.now() > 60


def test_d10_nikon_sdram_images_are_deleted(tmp_path):
    cam = EmulatedCamera(NIKON)
    _stack(cam, tmp_path, StackPlan(3, 5, settle_s=0.0))
    assert _ops(cam, OC.DeleteObject) == [(0xFFFF0001,)] * 3
    assert cam.objects == {} and cam.max_sdram_pending == 1


def test_d10_captured_files_are_readable_by_others(tmp_path):
    old = os.umask(0o022)
    try:
        _stack(EmulatedCamera(CANON), tmp_path, StackPlan(2, 5, settle_s=0.0))
    finally:
        os.umask(old)
    modes = {p.name: p.stat().st_mode & 0o777 for p in tmp_path.iterdir()}
    assert modes and set(modes.values()) == {0o644}, modes


def test_d10_list_without_a_camera_says_what_to_check(capsys):
    assert cli.main(["tether", "list", "--emulate", "none"]) == 0
    out = capsys.readouterr().out
    assert "PTP cameras: 0" in out
    assert all(word in out for word in ("USB mode to PTP", "gvfs", "permissions"))


def test_d10_emulated_nikon_stack_names_its_own_lens(tmp_path):
    assert cli.main(["tether", "stack", "-o", str(tmp_path), "--frames", "2", "--step", "5",
                     "--emulate", "nikon", "--settle-ms", "0"]) == 0
    meta = tomllib.loads((tmp_path / "stack.toml").read_text())
    lens = tomllib.loads((tmp_path / meta["lens"]).read_text())
    assert meta["lens"] == "lens.toml" and "emulated" in lens["name"]
    assert "canon" not in (tmp_path / "stack.toml").read_text().lower()


def test_d10_real_camera_needs_a_lens(tmp_path, capsys):
    assert cli.main(["tether", "stack", "-o", str(tmp_path), "--frames", "2",
                     "--step", "5"]) == 2
    assert "--lens is required with a real camera" in capsys.readouterr().err


# --- the strict emulator's other behaviours ----------------------------------------------


def test_hidden_operations_need_the_body_table(tmp_path):
    hidden = frozenset({NikonOC.MfDrive, NikonOC.StartLiveView})
    cam = EmulatedCamera(NIKON.but(hidden_ops=hidden))
    with pytest.raises(UnsupportedCamera, match=r"lacks StartLiveView \(0x9201\), MfDrive"):
        _stack(cam, tmp_path / "a", StackPlan(2, 5))
    result = _stack(EmulatedCamera(NIKON.but(hidden_ops=hidden)), tmp_path / "b",
                    StackPlan(2, 5, settle_s=0.0), known_operations=hidden)
    assert len(result.frames) == 2


def test_unplug_between_frames_keeps_what_was_downloaded(tmp_path):
    cam = EmulatedCamera(CANON)

    def pull(index, _name, _step):
        if index == 1:
            cam.unplug()

    with pytest.raises(DeviceGone, match="after 2 of 5 frames"):
        with connect(EmulatedBackend(cam)) as camera:
            capture_stack(camera, tmp_path, StackPlan(5, 5, settle_s=0.0), lens=LENS,
                          on_frame=pull)
    assert tomllib.loads((tmp_path / "stack.toml").read_text())["partial"] is True


def test_emulator_refuses_a_property_write_with_a_wrong_size():
    cam = EmulatedCamera(CANON)
    with connect(EmulatedBackend(cam)) as camera:
        response = camera.session.transaction(
            CanonOC.SetDevicePropValueEx, data_out=struct.pack("<III", 16, 0xD1B3, 1),
            check=False)
        assert response.code == 0x201D  # InvalidParameter: size field != data length


def test_emulated_nikon_bulb_answers_bulb_release_busy_until_terminated():
    cam = EmulatedCamera(NIKON)
    with connect(EmulatedBackend(cam)) as camera:
        cam.shutter = "bulb"  # mode dial turned after live view started
        s = camera.session
        s.transaction(NikonOC.InitiateCaptureRecInSdram, (0xFFFFFFFF,))
        camera.clock.sleep(1.0)
        assert s.transaction(NikonOC.DeviceReady, check=False, busy_ok=False).code == 0xA200
        s.transaction(NikonOC.TerminateCapture, (0, 0))
        assert camera.wait_ready() == 0x2001 and len(cam.shots) == 1
