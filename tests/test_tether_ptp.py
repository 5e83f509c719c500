"""PTP codec: containers, transfers and the ZLP rule, datasets, event records, schedules."""

from __future__ import annotations

import struct
import tomllib

import pytest
from hypothesis import given
from hypothesis import strategies as st

from pipeline.core.motion import Profile
from pipeline.tether.codes import ContainerType, response_name
from pipeline.tether.flows import drive_schedule, stack_toml_text
from pipeline.tether.ptp import (
    Container,
    DeviceInfo,
    ObjectInfo,
    ProtocolError,
    decode_container,
    encode_container,
    read_sizes,
    split_transfers,
)

u32 = st.integers(0, 0xFFFFFFFF)
u16 = st.integers(0, 0xFFFF)


@st.composite
def containers(draw):
    ctype = draw(st.sampled_from(list(ContainerType)))
    if ctype == ContainerType.DATA:
        return Container(ctype, draw(u16), draw(u32), payload=draw(st.binary(max_size=3000)))
    return Container(ctype, draw(u16), draw(u32), tuple(draw(st.lists(u32, max_size=5))))


@given(containers())
def test_container_round_trip(container):
    blob = encode_container(container)
    assert struct.unpack_from("<I", blob)[0] == len(blob)  # length field is the whole container
    assert decode_container(blob) == container


@given(containers(), st.sampled_from([8, 64, 512]), st.integers(1, 8))
def test_transfers_reassemble_and_end_with_zlp_on_full_packets(container, packet, per_transfer):
    blob = encode_container(container)
    chunks = split_transfers(blob, packet, packet * per_transfer)
    assert b"".join(chunks) == blob
    assert all(len(c) == packet * per_transfer for c in chunks[:-2])
    full = len(blob) % packet == 0  # the ZLP rule: a multiple of the packet size ends with b""
    assert (chunks[-1] == b"") == full


def test_exact_packet_multiple_payload_gets_a_zlp():
    blob = encode_container(Container(ContainerType.DATA, 0x1009, 7, payload=bytes(500)))
    assert len(blob) == 512
    assert split_transfers(blob, 512, 1024) == [blob, b""]


@given(st.integers(1, 5000), st.sampled_from([64, 512]), st.integers(1, 4))
def test_read_sizes_cover_the_container_in_packet_multiples(length, packet, per):
    sizes = read_sizes(length, packet, packet * per)
    assert all(s % packet == 0 for s in sizes)
    assert sum(sizes) >= length > sum(sizes[:-1])


def test_truncated_and_bad_headers_are_errors():
    blob = encode_container(Container(ContainerType.RESPONSE, 0x2001, 1, (5,)))
    with pytest.raises(ProtocolError, match="announces"):
        decode_container(blob[:-1])
    with pytest.raises(ProtocolError, match="type 9"):
        decode_container(struct.pack("<IHHI", 12, 9, 0, 0))


PTP_TEXT = st.text(st.characters(exclude_categories=("Cs",), exclude_characters="\x00"),
                   max_size=60)


@given(PTP_TEXT, st.lists(u16, max_size=40), u32)
def test_device_info_round_trip(model, ops, ext):
    info = DeviceInfo(vendor_extension_id=ext, manufacturer="Maker", model=model,
                      operations=tuple(ops))
    assert DeviceInfo.from_bytes(info.to_bytes()) == info


def test_object_info_round_trip():
    info = ObjectInfo(123456, "DSC_0001.TIF", 0x380D, 0x10001, 320, 224)
    assert ObjectInfo.from_bytes(info.to_bytes()) == info


def test_vendor_codes_are_resolved_per_vendor():
    assert response_name(0xA001, "canon").startswith("UnknownCommand")
    assert response_name(0xA001, "nikon").startswith("HardwareError")
    assert response_name(0xA00C, "nikon").startswith("MfDriveStepEnd")


def test_drive_schedule_matches_brute_force():
    profile = Profile([0.0, 0.4, 1.0], [30.5, 30.3, 30.3])  # move 0.2 mm, then pause
    step = 0.01
    schedule = drive_schedule(profile, step, period_s=0.01)
    assert sum(s for _t, s in schedule) == 20
    for t, _s in schedule:  # position reached after each command vs p(t) by hand
        done = sum(s for tt, s in schedule if tt <= t)
        expected = (30.5 - (30.5 - 0.5 * t)) / step if t <= 0.4 else 20
        assert abs(done - expected) <= 0.5 + 1e-9
    assert all(t <= 0.4 + 1e-9 for t, _s in schedule)  # nothing during the pause


def test_stack_toml_text_parses():
    text = stack_toml_text('lens "x"', [("a.jpg", 0), ("b.jpg", -12)], partial=True)
    data = tomllib.loads(text)
    assert data == {"lens": 'lens "x"', "kind": "focal-stack", "partial": True,
                    "frames": [{"file": "a.jpg", "focus_step": 0},
                               {"file": "b.jpg", "focus_step": -12}]}
    assert "partial" not in tomllib.loads(stack_toml_text("l", [("a", 1)]))
