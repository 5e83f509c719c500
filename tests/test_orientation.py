"""EXIF orientation: read as pillow and LibRaw read it, the result turned as OpenCV and
pillow turn a frame, and a carried EXIF block saying upright (pipeline.io.orientation)."""

from __future__ import annotations

import json
import logging
import shutil

import cv2
import numpy as np
import pytest
import tifffile
from hypothesis import example, given, settings
from hypothesis import strategies as st
from PIL import Image, ImageOps

from pipeline.errors import InputError
from pipeline.io.exif import read_exif
from pipeline.io.orientation import exif_orientation, upright, upright_exif
from pipeline.io.read import read_frame, read_preview
from pipeline.io.write import write_image
from pipeline.jobs.options import StackOptions
from pipeline.jobs.result import write_result
from pipeline.jobs.stack import process_stack


def _asymmetric(shape) -> np.ndarray:
    return (np.arange(int(np.prod(shape))) * 37 % 251).astype(np.uint8).reshape(shape)


@pytest.mark.parametrize("code", range(1, 9))
@pytest.mark.parametrize("channels", [0, 3])
def test_upright_turns_as_pillow_does(tmp_path, code, channels):
    """pillow's ``exif_transpose`` of a frame tagged ``code`` is the reference."""
    pixels = _asymmetric((5, 7, channels) if channels else (5, 7))
    path = tmp_path / "f.png"  # lossless: the stored pixels are exactly ``pixels``
    image = Image.fromarray(pixels)
    exif = image.getexif()
    exif[0x0112] = code
    image.save(path, exif=exif)
    with Image.open(path) as shown:
        expected = np.asarray(ImageOps.exif_transpose(shown))
    assert exif_orientation(path) == code
    np.testing.assert_array_equal(upright(pixels, code), expected)


def test_real_frames_read_as_pillow_and_libraw_read_them(shared_data):
    """Every real JPEG of the four stacks (all tagged, 1) and the real DNG."""
    frames = sorted(shared_data.glob("*/*.jpg")) + sorted(shared_data.glob("focusstack-pcb/*/*"))
    frames = [f for f in frames if f.suffix.lower() == ".jpg" and f.name != "expected.jpg"]
    assert len(frames) > 30
    for f in frames:
        with Image.open(f) as image:
            assert exif_orientation(f) == image.getexif().get(0x0112, 1), f
    dng = shared_data / "raw-dng-canon550d" / "colorchart.dng"
    with tifffile.TiffFile(dng) as tif:  # an independent reader of IFD0
        assert exif_orientation(dng) == tif.pages.first.tags["Orientation"].value == 1


@pytest.mark.parametrize("code", [3, 6, 8])
def test_a_turned_raw_frame_is_read_turned_and_decoded_as_stored(tmp_path, shared_data, code):
    """The real DNG with its IFD0 Orientation rewritten (tifffile, in place): flexdof reads
    the tag, and decodes the frame and its preview in the sensor's geometry, as before."""
    source = shared_data / "raw-dng-canon550d" / "colorchart.dng"
    turned = tmp_path / "turned.dng"
    shutil.copy(source, turned)
    with tifffile.TiffFile(turned, mode="r+b") as tif:
        tif.pages.first.tags["Orientation"].overwrite(code)
    assert exif_orientation(turned) == code
    np.testing.assert_array_equal(read_frame(turned), read_frame(source))
    np.testing.assert_array_equal(read_preview(turned, 400), read_preview(source, 400))


@settings(max_examples=30, deadline=None)
@given(
    code=st.integers(1, 8),
    other_tags=st.integers(0, 5),
    big_endian=st.booleans(),
    ext=st.sampled_from([".jpg", ".png"]),
)
@example(code=6, other_tags=5, big_endian=True, ext=".jpg")
def test_a_carried_block_says_upright_and_keeps_the_rest(
    tmp_path_factory, code, other_tags, big_endian, ext
):
    """pillow writes the block (the tag among others, either byte order); flexdof reads the
    tag, and the block it carries reads 1 in pillow with every other tag as it was."""
    exif = Image.Exif()
    exif.endian = ">" if big_endian else "<"
    names = (0x010E, 0x010F, 0x0110, 0x0131, 0x013B)
    for i in range(other_tags):
        exif[names[i]] = f"tag {i}"
    exif[0x0112] = code
    out = tmp_path_factory.mktemp("orientation") / f"f{ext}"
    write_image(out, np.zeros((4, 6), np.float32), exif=exif.tobytes())
    assert exif_orientation(out) == code
    carried = upright_exif(read_exif(out))
    shown = Image.Exif()
    shown.load(carried)
    assert shown[0x0112] == 1
    assert {t: shown[t] for t in names[:other_tags]} == {t: exif[t] for t in names[:other_tags]}
    assert len(carried) == len(read_exif(out))


def test_tiff_tags_and_missing_tags(tmp_path):
    tagged = tmp_path / "t.tif"
    tifffile.imwrite(tagged, np.zeros((4, 6), np.uint16), extratags=[(274, "H", 1, 8, True)])
    assert exif_orientation(tagged) == 8
    plain = tmp_path / "p.jpg"
    write_image(plain, np.zeros((4, 6), np.float32))
    assert exif_orientation(plain) == 1 and upright_exif(None) is None
    odd = Image.Exif()
    odd[0x0112] = 9  # not an EXIF orientation: the pixels as stored
    write_image(tmp_path / "o.jpg", np.zeros((4, 6), np.float32), exif=odd.tobytes())
    assert exif_orientation(tmp_path / "o.jpg") == 1


def _tagged_copies(sources, folder, codes):
    """The frames re-encoded once by pillow, tagged ``codes`` (pixels identical)."""
    folder.mkdir()
    paths = []
    for src, code in zip(sources, codes):
        with Image.open(src) as image:
            exif = image.getexif()
            exif[0x0112] = code
            image.save(folder / src.name, exif=exif, quality=95, subsampling=0)
        paths.append(folder / src.name)
    return paths


@pytest.mark.parametrize("code", [3, 6, 8])
def test_previews_are_in_the_frames_stored_geometry(tmp_path, shared_data, code):
    """A reduced JPEG decode (OpenCV's IMREAD_REDUCED_*) applies the EXIF orientation unless
    told not to; a preview must show the frame as :func:`read_frame` decodes it, as stored,
    or the alignment and the focus maps fit a turned frame (a portrait stack came out with
    0 of 9 regions as good as focus-stack)."""
    source = shared_data / "chimpstackr-beetle" / "DSC_0356.jpg"
    (path,) = _tagged_copies([source], tmp_path / "t", [code])
    frame = read_frame(path).mean(axis=2)
    preview = read_preview(path, 375)  # a 1/2 DCT-domain decode of 750 x 500
    assert preview.shape == (250, 375) == (frame.shape[0] // 2, frame.shape[1] // 2)
    expected = cv2.resize(frame, (375, 250), interpolation=cv2.INTER_AREA)
    assert np.abs(preview - expected).mean() < 0.03 * expected.mean()  # 1.1% measured


def test_a_portrait_stack_comes_out_upright(tmp_path, shared_data, caplog):
    """A stack shot with the camera turned (tag 6, a quarter clockwise): the result is the
    untagged stack's turned as OpenCV shows the frames, its sidecar says so, and a JPEG
    output's carried EXIF says upright; a frame tagged otherwise is named in a warning."""
    sources = sorted((shared_data / "chimpstackr-beetle").glob("*.jpg"))[:4]
    plain = _tagged_copies(sources, tmp_path / "plain", [1] * 4)
    turned = _tagged_copies(sources, tmp_path / "turned", [6] * 4)
    options = StackOptions()
    flat = process_stack(plain, tmp_path / "plain.tif", options)
    portrait = process_stack(turned, tmp_path / "turned.tif", options)
    shown = cv2.imread(str(turned[0]))  # OpenCV applies the EXIF orientation
    written = cv2.imread(str(tmp_path / "turned.tif"), cv2.IMREAD_UNCHANGED)
    assert written.shape[:2] == shown.shape[:2] != flat.image.shape[:2]
    np.testing.assert_array_equal(
        written, upright(cv2.imread(str(tmp_path / "plain.tif"), cv2.IMREAD_UNCHANGED), 6)
    )
    # and the float images too. Under OpenCV 5.1 one pixel of 1.1 M once differed by an ulp
    # in the full suite: its bilinear warpPerspective gave results that depend on how its
    # thread pool split the rows, which depends on whether the other accumulation lane
    # held the pool (stop 42; the warp now goes through cv2.remap, tests/test_align.py)
    np.testing.assert_array_equal(portrait.image, upright(flat.image, 6))
    side = json.loads((tmp_path / "turned.tif.json").read_text())
    assert side["orientation"] == 6 and flat.sidecar["orientation"] == 1
    # the sidecar's homographies stay in the frames' stored geometry
    assert side["frames"][0]["homography"] == flat.sidecar["frames"][0]["homography"]

    mixed = turned[:3] + _tagged_copies(sources[3:], tmp_path / "mixed", [1])
    with caplog.at_level(logging.WARNING):
        jpeg = process_stack(mixed, tmp_path / "mixed.jpg", options)
    assert any(sources[3].name in r.getMessage() for r in caplog.records)
    assert jpeg.image.shape == portrait.image.shape
    with Image.open(tmp_path / "mixed.jpg") as out:
        assert out.getexif()[0x0112] == 1  # a viewer must not turn it again
        assert out.size == (shown.shape[1], shown.shape[0])


def test_the_saved_kernel_is_turned_with_the_image(tmp_path):
    """An asymmetric kernel (a lens's PSF need not be symmetric) is saved as the image is
    written: turned the same way, so that it is the blur of the upright image."""
    frame = tmp_path / "f.jpg"
    exif = Image.Exif()
    exif[0x0112] = 8
    write_image(frame, np.zeros((4, 6), np.float32), exif=exif.tobytes())
    kernel = np.zeros((5, 5), np.float32)
    kernel[0, 1], kernel[2, 2], kernel[3, 4] = 0.2, 0.5, 0.3
    image = np.linspace(0, 1, 4 * 6, dtype=np.float32).reshape(4, 6)
    options = StackOptions(encoding="float32", save_kernel=tmp_path / "k.tif")
    sidecar = {"kernel": {}}
    written = write_result(tmp_path / "o.tif", image, kernel, sidecar, {}, 0.0, options, [frame])
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "o.tif"), np.rot90(image))
    np.testing.assert_array_equal(tifffile.imread(tmp_path / "k.tif"), np.rot90(kernel))
    np.testing.assert_array_equal(written.image, np.rot90(image))
    assert sidecar["orientation"] == 8


def test_a_frame_saved_turned_by_a_viewer_is_named_with_the_reason(tmp_path, shared_data):
    """One frame rotated and saved again (portrait pixels, tag 1) among frames stored in
    landscape with tag 6: one line naming the file, its size and the likely cause."""
    from pipeline.cli import main

    sources = sorted((shared_data / "chimpstackr-beetle").glob("*.jpg"))[:3]
    (tmp_path / "f").mkdir()
    for i, src in enumerate(sources):
        with Image.open(src) as image:
            if i == 1:
                image.transpose(Image.Transpose.ROTATE_270).save(tmp_path / "f" / src.name)
            else:
                exif = image.getexif()
                exif[0x0112] = 6
                image.save(tmp_path / "f" / src.name, exif=exif)
    with pytest.raises(InputError, match=rf"{sources[1].name}: 500x750 px.*stored turned"):
        process_stack(tmp_path / "f", tmp_path / "o.tif", StackOptions())
    assert main(["-q", "stack", str(tmp_path / "f"), "-o", str(tmp_path / "o.tif")]) == 2
    assert not (tmp_path / "o.tif").exists()
