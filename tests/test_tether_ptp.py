"""PTP codec: containers, transfers and the ZLP rule, datasets, event records, schedules."""

from __future__ import annotations

import dataclasses
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
    Reader,
    container_length,
    decode_container,
    encode_container,
    iter_chunks,
    pack_array,
    pack_string,
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


# --- the codec's rules against hand-built bytes ------------------------------------------------


def test_containers_carry_at_most_five_parameters_or_else_a_payload():
    assert Container(ContainerType.RESPONSE, 0x2001, 1, (1, 2, 3, 4, 5)).params == (1, 2, 3, 4, 5)
    with pytest.raises(ProtocolError, match="at most 5 parameters"):
        Container(ContainerType.COMMAND, 0x1001, 1, (1, 2, 3, 4, 5, 6))
    with pytest.raises(ProtocolError, match="payload, not parameters"):
        Container(ContainerType.DATA, 0x1001, 1, (1,))
    for ctype in (ContainerType.COMMAND, ContainerType.RESPONSE, ContainerType.EVENT):
        with pytest.raises(ProtocolError, match=f"not {ctype.name}"):
            Container(ctype, 0x1001, 1, payload=b"x")


def test_headers_and_parameter_bytes_are_validated():
    with pytest.raises(ProtocolError, match="12-byte header: 11 bytes"):
        container_length(bytes(11))
    assert container_length(struct.pack("<IHHI", 12, 3, 0x2001, 1) + b"...") == 12
    with pytest.raises(ProtocolError, match="length 11, type 3"):
        container_length(struct.pack("<IHHI", 11, 3, 0x2001, 1))
    for ctype in (0, 5):
        with pytest.raises(ProtocolError, match=f"type {ctype} "):
            container_length(struct.pack("<IHHI", 12, ctype, 0x2001, 1))
    for ctype in (1, 2, 3, 4):
        assert container_length(struct.pack("<IHHI", 16, ctype, 0x1001, 1)) == 16
    five = struct.pack("<IHHI5I", 32, 3, 0x2001, 7, 1, 2, 3, 4, 5)
    assert decode_container(five) == Container(ContainerType.RESPONSE, 0x2001, 7, (1, 2, 3, 4, 5))
    with pytest.raises(ProtocolError, match="announces 32 bytes but 33 arrived"):
        decode_container(five + b"\x00")
    with pytest.raises(ProtocolError, match="RESPONSE container has 24 parameter bytes"):
        decode_container(struct.pack("<IHHI6I", 36, 3, 0x2001, 7, 1, 2, 3, 4, 5, 6))
    with pytest.raises(ProtocolError, match="COMMAND container has 3 parameter bytes"):
        decode_container(struct.pack("<IHHI", 15, 1, 0x1001, 7) + b"abc")
    data = decode_container(struct.pack("<IHHI", 36, 2, 0x1009, 7) + bytes(range(24)))
    assert data.payload == bytes(range(24)) and data.params == ()  # no limit on a payload


def test_transfer_split_and_read_sizes_by_hand():
    assert split_transfers(bytes(1000), 512, 512) == [bytes(512), bytes(488)]
    assert split_transfers(bytes(1024), 512, 512) == [bytes(512), bytes(512), b""]
    assert split_transfers(bytes(1024), 512, 2048) == [bytes(1024), b""]
    assert split_transfers(bytes(100), 64, 128) == [bytes(100)]
    assert split_transfers(b"abc", 1, 1) == [b"a", b"b", b"c", b""]  # 1-byte packets: valid
    for packet, most in ((0, 512), (512, 0), (-512, -512), (512, 768)):
        with pytest.raises(ValueError, match="positive multiple"):
            split_transfers(bytes(10), packet, most)
    assert read_sizes(0, 512, 1024) == []
    assert read_sizes(1, 512, 1024) == [512]
    assert read_sizes(512, 512, 1024) == [512]
    assert read_sizes(1000, 512, 1024) == [1024]
    assert read_sizes(1025, 512, 1024) == [1024, 512]
    assert read_sizes(2048, 512, 1024) == [1024, 1024]


def test_a_string_of_only_its_terminator_is_empty_and_read_past():
    """Some bodies send an empty string as one character (the NUL, count 1) rather than
    count 0: it reads as "" and the next field starts two bytes later."""
    r = Reader(b"\x01\x00\x00\x07\x00", "DeviceInfo")
    assert r.string() == ""
    assert r.pos == 3 and r.take("H") == 7


def test_a_negative_packet_size_is_refused():
    """wMaxPacketSize is unsigned; a negative size (a bug upstream) is an error, not a split
    whose modulo happens to be 0 (512 % -512 == 0 in Python)."""
    with pytest.raises(ValueError, match="positive multiple"):
        split_transfers(b"x" * 600, -512, 512)


def test_dataset_reader_and_strings_by_hand():
    r = Reader(b"\x01\x02\x03", "Thing")
    assert r.take("B") == 1 and r.take("H") == 0x0302 and r.pos == 3
    with pytest.raises(ProtocolError, match="Thing dataset truncated at byte 3"):
        r.take("B")
    with pytest.raises(ProtocolError, match="truncated at byte 0"):
        Reader(b"\x01\x00\x00", "X").take("I")
    assert Reader(b"\x02\x00\x00\x00\x05\x00\x06\x00", "X").array("H") == (5, 6)
    assert Reader(b"\x00", "X").string() == ""
    assert Reader(b"\x03A\x00B\x00\x00\x00", "X").string() == "AB"
    with pytest.raises(ProtocolError, match="inside a string"):
        Reader(b"\x03A\x00B\x00\x00", "X").string()  # one byte short
    assert pack_string("") == b"\x00"
    assert pack_string("AB") == b"\x03A\x00B\x00\x00\x00"
    assert pack_string("x" * 254)[0] == 255 and len(pack_string("x" * 254)) == 511
    assert Reader(pack_string("y" * 254), "X").string() == "y" * 254  # the longest string
    with pytest.raises(ValueError, match="at most 254"):
        pack_string("x" * 255)
    assert pack_array("H", [1, 2]) == b"\x02\x00\x00\x00\x01\x00\x02\x00"
    assert pack_array("I", []) == b"\x00\x00\x00\x00"
    assert list(iter_chunks(10, 4)) == [(0, 4), (4, 4), (8, 2)]
    assert list(iter_chunks(8, 4)) == [(0, 4), (4, 4)] and list(iter_chunks(0, 4)) == []


def test_device_info_bytes_by_hand():
    info = DeviceInfo(vendor_extension_id=0xB, manufacturer="M", model="X", operations=(0x1001,),
                      events=(0x4002,), properties=(0x5001, 0x5003), standard_version=110,
                      vendor_extension_version=120, vendor_extension_desc="d",
                      functional_mode=1, capture_formats=(0x3801,), image_formats=(0x3000,),
                      device_version="2", serial_number="S")

    def s(c):
        return b"\x02" + c.encode("utf-16-le") + b"\x00\x00"

    def arr(*v):
        return struct.pack(f"<I{len(v)}H", len(v), *v)

    expected = (struct.pack("<HIH", 110, 0xB, 120) + s("d") + struct.pack("<H", 1)
                + arr(0x1001) + arr(0x4002) + arr(0x5001, 0x5003) + arr(0x3801) + arr(0x3000)
                + s("M") + s("X") + s("2") + s("S"))
    assert info.to_bytes() == expected
    assert DeviceInfo.from_bytes(expected) == info
    with pytest.raises(ProtocolError, match="DeviceInfo dataset truncated"):
        DeviceInfo.from_bytes(expected[:-1])


def test_device_info_defaults_are_ptp_1_00_with_no_extension_text():
    blob = DeviceInfo(vendor_extension_id=0xB, manufacturer="", model="", operations=()).to_bytes()
    # StandardVersion u16 = 100 (PTP 1.00), extension id u32, extension version u16 = 100,
    # empty extension description (one 0 byte), FunctionalMode u16 = 0 (standard mode)
    assert blob[:11] == struct.pack("<HIH", 100, 0xB, 100) + b"\x00" + struct.pack("<H", 0)


def test_containers_and_datasets_are_immutable_values():
    values = [Container(ContainerType.COMMAND, 0x1001, 1, (1,)),
              DeviceInfo(vendor_extension_id=0xB, manufacturer="M", model="X", operations=()),
              ObjectInfo(1, "A.JPG")]
    for value in values:
        with pytest.raises(dataclasses.FrozenInstanceError):
            value.code = 2
    assert len(set(values)) == 3  # hashable: usable as keys


def test_object_info_leaves_unset_fields_zero_and_needs_its_file_name():
    blob = ObjectInfo(1234, "IMG.JPG").to_bytes()
    # ISO 15740 5.5.2: format u16 at 4, compressed size u32 at 8; every other field of the
    # 52-byte head (storage, protection, thumbnail, image size/depth, parent, ...) is 0
    assert blob[4:6] == b"\x01\x38" and blob[8:12] == struct.pack("<I", 1234)
    assert blob[0:4] + blob[6:8] + blob[12:52] == bytes(46)
    assert blob[52] == 8 and blob[53:69].decode("utf-16-le") == "IMG.JPG\x00"
    assert blob[69:] == b"\x00\x00\x00"  # capture date, modification date, keywords: empty
    assert ObjectInfo.from_bytes(blob[:52] + b"\x00") == ObjectInfo(1234, "")  # empty name
    with pytest.raises(ProtocolError, match="too short: 52 bytes"):
        ObjectInfo.from_bytes(blob[:52])


# --- mutation kills (helper mut11) -------------------------------------------------------------


def test_a_negative_transfer_size_is_refused_even_when_a_packet_multiple():
    with pytest.raises(ValueError, match="positive multiple"):
        split_transfers(bytes(10), 512, -512)  # -512 % 512 == 0: only the sign refuses it

