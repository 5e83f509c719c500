"""ICC profiles (pipeline.io.icc): read as pillow reads them, carried into every sRGB-coded
output so that pillow reads the same bytes back, and into a stack's result."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from pipeline.io.icc import read_icc
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack


@pytest.fixture(scope="module")
def profile(shared_data) -> bytes:
    """The real sRGB profile (3144 bytes) amber's camera embedded in its JPEGs."""
    with Image.open(shared_data / "shinestacker-amber" / "0000.jpg") as image:
        return image.info["icc_profile"]


def test_a_real_frames_profile_reads_as_pillow_reads_it(shared_data, profile):
    assert len(profile) == 3144
    assert read_icc(shared_data / "shinestacker-amber" / "0000.jpg") == profile
    assert read_icc(shared_data / "focusstack-pcb" / "pcb7" / "pcb_001.jpg") is None
    assert read_icc(shared_data / "raw-dng-canon550d" / "colorchart.dng") is None


@pytest.mark.parametrize(
    ("name", "encoding"), [("o.jpg", None), ("o.png", None), ("o.png", "srgb16"),
                           ("o.tif", None), ("o.tif", "srgb8")],
)  # fmt: skip
@pytest.mark.parametrize("padding", [0, 150_000])  # 150 kB: three JPEG APP2 chunks
def test_sRGB_coded_outputs_carry_it_for_pillow(tmp_path, profile, name, encoding, padding):
    """The bytes are transported, not interpreted (the padded profile is no valid ICC
    file); pillow, an independent reader of all three containers, reads them back."""
    carried = profile + bytes(range(256)) * (padding // 256)
    image = np.linspace(0, 1, 12 * 16 * 3, dtype=np.float32).reshape(12, 16, 3)
    exif = Image.Exif()
    exif[0x0110] = "a model"
    write_image(tmp_path / name, image, encoding=encoding, icc=carried, exif=exif.tobytes())
    with Image.open(tmp_path / name) as written:
        assert written.info["icc_profile"] == carried
        if not name.endswith(".tif"):
            assert written.getexif()[0x0110] == "a model"  # EXIF still there, and first
    assert read_icc(tmp_path / name) == carried
    assert read_frame(tmp_path / name).shape == (12, 16, 3)


def test_linear_outputs_carry_none(tmp_path, profile):
    for encoding in ("linear16", "float32"):
        write_image(tmp_path / f"{encoding}.tif", np.zeros((4, 4, 3), np.float32),
                    encoding=encoding, icc=profile)  # fmt: skip
        assert read_icc(tmp_path / f"{encoding}.tif") is None


def test_a_stacks_result_carries_its_first_frames_profile(tmp_path, shared_data, profile):
    """Beetle's frames saved with the profile (by pillow): the result, a 16-bit TIFF and a
    JPEG, carries it; the untagged stack's result carries none."""
    sources = sorted((shared_data / "chimpstackr-beetle").glob("*.jpg"))[:3]
    (tmp_path / "f").mkdir()
    for src in sources:
        with Image.open(src) as image:
            image.save(tmp_path / "f" / src.name, quality=95, icc_profile=profile)
    for out in ("r.tif", "r.jpg"):
        process_stack(tmp_path / "f", tmp_path / out, StackOptions())
        assert read_icc(tmp_path / out) == profile
    process_stack(sources, tmp_path / "plain.tif", StackOptions())
    assert read_icc(tmp_path / "plain.tif") is None


def test_jpeg_chunks_are_joined_by_their_sequence_numbers(tmp_path, profile):
    """ICC.1 B.4 orders the chunks by their sequence number, not by their place in the file:
    the chunks of a written JPEG swapped in place still read as the profile."""
    carried = profile + bytes(range(256)) * 600  # 157 kB: three chunks
    write_image(tmp_path / "o.jpg", np.zeros((8, 8), np.float32), icc=carried)
    data = (tmp_path / "o.jpg").read_bytes()
    starts = [i for i in range(len(data) - 16) if data[i : i + 2] == b"\xff\xe2"]
    spans = [(s, s + 2 + int.from_bytes(data[s + 2 : s + 4], "big")) for s in starts[:3]]
    chunks = [data[a:b] for a, b in spans]
    assert [c[16] for c in chunks] == [1, 2, 3]  # the sequence numbers, as written
    swapped = data[: spans[0][0]] + chunks[2] + chunks[1] + chunks[0] + data[spans[-1][1] :]
    (tmp_path / "s.jpg").write_bytes(swapped)
    assert read_icc(tmp_path / "s.jpg") == carried
