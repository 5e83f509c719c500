"""Which real bodies the tether flows accept, decided from their GetDeviceInfo listings.

The listings are libgphoto2's per-body ``gphoto2 --summary`` outputs
(``shared/data/ptp-recordings/libgphoto2-cameras``). The decision
(:func:`pipeline.tether.capabilities.body_capability`) must agree with the
drivers' own ``check_supported``, which the connect path runs.
"""

from __future__ import annotations

import functools
import importlib.util
import sys
from pathlib import Path

import pytest

from pipeline.errors import InputError
from pipeline.tether.canon import CanonEOS
from pipeline.tether.capabilities import (
    CanonLiveViewOC,
    body_capability,
    device_info_from_listing,
    vendor_of,
)
from pipeline.tether.codes import OC, CanonOC, NikonOC
from pipeline.tether.dispatch import camera_for
from pipeline.tether.emulated.device import EmulatedBackend, EmulatedCamera
from pipeline.tether.emulated.personalities import CANON
from pipeline.tether.flows import connect
from pipeline.tether.nikon import Nikon
from pipeline.tether.ptp import DeviceInfo
from pipeline.tether.session import PtpSession, UnsupportedCamera

SCRIPT = Path(__file__).resolve().parent / "benchmarks" / "tether_bodies.py"


@functools.cache
def _script():
    """The table generator ``tests/benchmarks/tether_bodies.py`` as a module."""
    spec = importlib.util.spec_from_file_location("tether_bodies", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass needs the module registered
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def listings(shared_data) -> Path:
    return shared_data / "ptp-recordings" / "libgphoto2-cameras"


@pytest.fixture(scope="module")
def table(listings):
    return _script().body_table(listings)


def test_body_table_counts(table):
    summary = _script().summary(table)
    assert summary["listings"] == len(table) == 115
    assert summary["with an operation list"] == 78
    assert summary["focal stack accepted"] == 58
    assert summary["sweep accepted"] == 36  # the Canon bodies that can stack
    assert summary["focal stack refused"] == 20
    assert summary["sweep refused"] == 42
    refusals = {k: v for k, v in summary.items() if k.startswith(("stack and", "sweep only"))}
    assert refusals == {
        "sweep only: Nikon: sweep not supported": 22,  # every Nikon body that can stack
        "stack and sweep: no live view / MfDrive in GetDeviceInfo": 9,
        "stack and sweep: lists no Nikon vendor operations": 4,
        "stack and sweep: no live view or DriveLens in GetDeviceInfo": 3,
        "stack and sweep: only the one-shot RemoteRelease, no RemoteReleaseOn/Off": 3,
        "stack and sweep: no EOS remote-control operations": 1,
    }
    assert summary[_script().NO_LIST] == 37


NIKON_NO_SWEEP = "Nikon: sweep not supported (live view is prohibited in bulb; no bulb path)"

KNOWN_BODIES = [
    ("canon-eos60d.txt", "Canon EOS 60D", True, True, ""),
    ("canon-eos-1000d.txt", "Canon EOS 1000D", False, False,
     "only the one-shot RemoteRelease, no RemoteReleaseOn/Off (lacks RemoteReleaseOn (0x9128), "
     "RemoteReleaseOff (0x9129))"),
    ("canon-eos350d.txt", "Canon EOS 350D DIGITAL", False, False,
     "no EOS remote-control operations"),
    ("canon-eos-r100.txt", "Canon EOS R100", True, True, ""),  # vendor extension 0x6
    ("nikon-d3300.txt", "D3300", False, False,
     "lists no Nikon vendor operations (live view, MfDrive and SDRAM capture hidden) (lacks "
     "StartLiveView (0x9201), EndLiveView (0x9202), MfDrive (0x9204)"),
    ("nikon-d90.txt", "D90", True, False, NIKON_NO_SWEEP),
    ("nikon-d7000.txt", "D7000", True, False, NIKON_NO_SWEEP),  # lists without headers
    ("nikon-d5300.txt", "D5300", True, False, NIKON_NO_SWEEP),  # codes followed by their names
    ("nikon-z9.txt", "Z 9", True, False, NIKON_NO_SWEEP),
]


@pytest.mark.parametrize(("listing", "model", "stack", "sweep", "reason"), KNOWN_BODIES,
                         ids=[body[0] for body in KNOWN_BODIES])
def test_known_bodies(listings, listing, model, stack, sweep, reason):
    info = device_info_from_listing(listings / listing)
    cap = body_capability(info)
    assert (cap.model, cap.stack, cap.sweep) == (model, stack, sweep)
    assert (cap.stack_reason or cap.sweep_reason).startswith(reason)
    assert bool(reason) == (not cap.sweep)


def test_listing_parser_reads_all_three_lists(listings):
    info = device_info_from_listing(listings / "canon-eos-1000d.txt")
    assert info.manufacturer == "Canon Inc." and info.vendor_extension_id == 0xB
    assert len(info.operations) == 65  # including the four after a blank line
    assert info.operations[:2] == (OC.GetDeviceInfo, OC.OpenSession)
    assert 0x91F0 in info.operations and info.operations[-1] == 0x9805
    assert info.events == (0x4002, 0x4003, 0x4004, 0x4005, 0x4007, 0x4009, 0xC101)
    assert info.properties == (0xD402, 0xD407, 0xD406)
    z9 = device_info_from_listing(listings / "nikon-z9.txt")
    assert z9.vendor_extension_id == 0xA  # of the two equal blocks, the one with Nikon's id
    d7000 = device_info_from_listing(listings / "nikon-d7000.txt")
    assert (len(d7000.operations), len(d7000.events), len(d7000.properties)) == (47, 15, 210)
    assert device_info_from_listing(listings / "canon-eos-r5.txt") is None  # config dump only


def test_decision_agrees_with_the_drivers_check_supported(table, listings):
    """The connect path runs ``camera_for(session).check_supported``: same answer, every body."""
    checked = 0
    for row in table:
        if row.capability is None:
            continue
        info = device_info_from_listing(listings / row.file)
        session = PtpSession(transport=None)
        session.device_info, session.vendor = info, vendor_of(info)
        driver = camera_for(session)
        for bulb, accepted in ((False, row.capability.stack), (True, row.capability.sweep)):
            if accepted:
                driver.check_supported(bulb=bulb)
            else:
                with pytest.raises(UnsupportedCamera, match=f"{info.model} cannot"):
                    driver.check_supported(bulb=bulb)
        checked += 1
    assert checked == 78


def test_markdown_table_is_up_to_date(table):
    committed = (SCRIPT.parent / "results" / "tether_bodies.md").read_text()
    assert committed == _script().markdown(table), (
        "regenerate with: python tests/benchmarks/tether_bodies.py"
    )


# --- the decision on synthetic device infos ---------------------------------------------------


def _info(ops, *, ext=0xB, maker="Canon Inc.", model="Test body") -> DeviceInfo:
    return DeviceInfo(vendor_extension_id=ext, manufacturer=maker, model=model,
                      operations=tuple(ops))


def test_vendor_from_extension_id_or_manufacturer():
    assert vendor_of(_info((), ext=0x6)) == "canon"  # what a real EOS sends
    assert vendor_of(_info((), ext=0xFFFFFFFF, maker="Nikon Corporation")) == "nikon"
    assert vendor_of(_info((), ext=0xA, maker="")) == "nikon"
    cap = body_capability(_info(CanonEOS.stack_ops, ext=0x6, maker="Sony Corporation"))
    assert not cap.stack and not cap.sweep and cap.vendor is None
    assert cap.stack_reason.startswith("not a Canon EOS or Nikon body (vendor extension 0x6")


def test_canon_reasons():
    full = set(CanonEOS.stack_ops)
    assert body_capability(_info(full)).stack
    no_drive = body_capability(_info(full - {CanonOC.DriveLens}
                                     | {CanonLiveViewOC.GetViewFinderData}))
    assert no_drive.stack_missing == (CanonOC.DriveLens,)
    assert no_drive.stack_reason == ("live view but no DriveLens in GetDeviceInfo "
                                     "(lacks DriveLens (0x9155))")


def test_nikon_sweep_is_refused_whatever_the_body_lists():
    ops = set(Nikon.stack_ops) | {NikonOC.TerminateCapture}
    cap = body_capability(_info(ops, ext=0xA, maker="Nikon Corporation", model="D850"))
    assert cap.stack and not cap.sweep and cap.sweep_missing == ()
    assert cap.sweep_reason == Nikon.sweep_refusal == NIKON_NO_SWEEP
    assert cap.category == "Nikon: sweep not supported"
    assert cap.refusal() == ""
    assert cap.refusal(sweep=True) == (f"D850 cannot run a focus sweep: {NIKON_NO_SWEEP}; "
                                       "capture a focal stack (tether stack) instead")
    # a Nikon body that cannot stack is refused the sweep for the same missing operations
    short = body_capability(_info(ops - {NikonOC.MfDrive}, ext=0xA))
    assert short.sweep_missing == short.stack_missing == (NikonOC.MfDrive,)
    assert short.sweep_reason == short.stack_reason


def test_hidden_operations_count_when_the_body_table_names_them():
    ops = set(CanonEOS.stack_ops) - {CanonOC.DriveLens}
    assert not body_capability(_info(ops)).stack
    cap = body_capability(_info(ops), extra_operations={CanonOC.DriveLens})
    assert cap.stack and cap.sweep


def test_the_decision_uses_the_drivers_own_requirements(monkeypatch):
    """A driver that starts needing another operation changes the decision with it."""
    ops = set(CanonEOS.stack_ops)
    assert body_capability(_info(ops)).stack
    monkeypatch.setattr(CanonEOS, "stack_ops", (*CanonEOS.stack_ops, OC.GetObjectInfo))
    cap = body_capability(_info(ops))
    assert not cap.stack and cap.stack_missing == (OC.GetObjectInfo,)
    monkeypatch.setattr(CanonEOS, "sweep_refusal", "no bulb path here")
    assert body_capability(_info(ops | {OC.GetObjectInfo})).sweep_reason == "no bulb path here"


def test_listing_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match=r"nowhere.txt: cannot read the listing"):
        device_info_from_listing(tmp_path / "nowhere.txt")
    bad = tmp_path / "bad.txt"
    bad.write_text("Manufacturer: Canon Inc.\nVendor extension ID: none\nSupported operations:\n"
                   "  0x1001\n")
    with pytest.raises(InputError, match=r"bad.txt:2: 'Vendor extension ID' is not a hex number"):
        device_info_from_listing(bad)


# --- the decision on the connect path, through the emulator -----------------------------------


@pytest.mark.parametrize(("bulb", "hidden", "line"), [
    (False, {CanonOC.DriveLens},
     "Canon EOS 60D (emulated) cannot capture a focal stack: no live view or DriveLens in "
     "GetDeviceInfo (lacks DriveLens (0x9155))"),
    (True, {CanonOC.RemoteReleaseOn, CanonOC.RemoteReleaseOff},
     "Canon EOS 60D (emulated) cannot run a focus sweep: only the one-shot RemoteRelease, no "
     "RemoteReleaseOn/Off (lacks RemoteReleaseOn (0x9128), RemoteReleaseOff (0x9129))"),
])
def test_connect_refuses_a_body_hiding_an_operation_before_any_capture(bulb, hidden, line):
    cam = EmulatedCamera(CANON.but(hidden_ops=frozenset(hidden)))
    with pytest.raises(UnsupportedCamera) as caught:
        with connect(EmulatedBackend(cam), bulb=bulb):
            pytest.fail("a refused body must not reach the flow")
    assert str(caught.value) == line and "\n" not in line
    # the session opened, was judged and closed: no remote mode, live view, drive or shot
    assert [op for _tid, op, _params in cam.transactions] == [OC.GetDeviceInfo, OC.OpenSession,
                                                              OC.CloseSession]
    assert not cam.shots and not cam.session_open


def test_connect_accepts_the_hidden_operation_the_body_table_names():
    hidden = frozenset({CanonOC.DriveLens})
    cam = EmulatedCamera(CANON.but(hidden_ops=hidden))
    with connect(EmulatedBackend(cam), known_operations=hidden) as camera:
        camera.drive(2)
    assert [params for _tid, op, params in cam.transactions if op == CanonOC.DriveLens] == [
        (0x8001,), (0x8001,)]


def test_tether_list_prints_the_decision_for_stack_and_sweep(capsys):
    from pipeline import cli

    assert cli.main(["tether", "list", "--emulate", "nikon"]) == 0
    line = capsys.readouterr().out.splitlines()[1]
    assert line.startswith("04b0:0429  Nikon Corporation Nikon D5100 (emulated)")
    assert line.endswith(f"focal stack: yes  sweep: no ({NIKON_NO_SWEEP})")
    assert cli.main(["tether", "list", "--emulate", "canon", "--personality", "eos-r"]) == 0
    assert capsys.readouterr().out.splitlines()[1].endswith("focal stack: yes  sweep: yes")
