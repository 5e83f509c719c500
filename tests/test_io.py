"""pipeline.io (read, write, probe, exif): decoding to linear light, encoding, bad files."""

from __future__ import annotations

import math
import os

import cv2
import numpy as np
import pytest
import rawpy
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from pipeline.core.colour import linear_to_srgb, srgb_to_linear
from pipeline.errors import InputError
from pipeline.io.exif import read_exif, subject_distance_mm
from pipeline.io.icc import read_icc
from pipeline.io.orientation import exif_orientation
from pipeline.io.probe import frame_info
from pipeline.io.read import read_frame
from pipeline.io.write import write_image, write_json


def eotf(codes, top):
    """The sRGB EOTF (IEC 61966-2-1) written out independently, float64."""
    c = np.asarray(codes, dtype=np.float64) / top
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def ramp(shape, rng):
    """A smooth linear-light test image in [0, 1] with a few exact 0s and 1s."""
    image = rng.random(shape).astype(np.float32)
    image.flat[0], image.flat[-1] = 0.0, 1.0
    return image


# --- sRGB transfer functions -----------------------------------------------------------------


def test_srgb_known_values():
    # Reference values of the sRGB standard's formulas (also in e.g. colour-science).
    assert srgb_to_linear(np.float64(0.5)) == pytest.approx(0.21404114048223255, rel=1e-12)
    assert linear_to_srgb(np.float64(0.18)) == pytest.approx(0.4613561295004128, rel=1e-12)
    assert srgb_to_linear(np.float64(0.04045)) == pytest.approx(0.04045 / 12.92)
    assert linear_to_srgb(np.float64(1.0)) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize(
    ("dtype", "out"), [(np.float32, np.float32), (np.float64, np.float64), (np.uint8, np.float64)]
)
def test_srgb_dtype_policy(dtype, out):
    x = np.array([0, 1], dtype=dtype)
    assert srgb_to_linear(x).dtype == out
    assert linear_to_srgb(x).dtype == out


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 1.0))
def test_srgb_round_trip(value):
    x = np.float64(value)
    # The standard's thresholds (0.04045 and 0.0031308 = 0.04045 / 12.92 - 5e-9) do not
    # match exactly, so the round trip near the knee is exact only to ~1e-7.
    assert srgb_to_linear(linear_to_srgb(x)) == pytest.approx(x, abs=1e-7)
    assert linear_to_srgb(srgb_to_linear(x)) == pytest.approx(x, abs=1e-7)


def test_srgb_float32_accuracy():
    x = np.linspace(0, 1, 100001, dtype=np.float32)
    back = srgb_to_linear(linear_to_srgb(x))
    assert back.dtype == np.float32
    assert np.max(np.abs(back - x)) < 2e-6


# --- decoding of integer and float files written by other libraries -----------------------


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize(("ext", "dtype"), [(".png", np.uint8), (".png", np.uint16)])
def test_png_decodes_with_srgb_eotf(tmp_path, ext, dtype, channels):
    top = np.iinfo(dtype).max
    rng = np.random.default_rng(1)
    shape = (17, 23) if channels == 1 else (17, 23, 3)
    codes = rng.integers(0, top + 1, shape, dtype=dtype)
    path = tmp_path / f"img{ext}"
    assert cv2.imwrite(str(path), codes if channels == 1 else codes[:, :, ::-1])  # RGB -> BGR
    image = read_frame(path)
    assert image.dtype == np.float32 and image.shape == shape
    np.testing.assert_allclose(image, eotf(codes, top), rtol=1e-6, atol=1e-9)
    assert frame_info(path).shape == shape


@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_tiff_decoding(tmp_path, dtype, planar):
    rng = np.random.default_rng(2)
    if np.dtype(dtype).kind == "f":
        data = rng.random((9, 11, 3)).astype(dtype) * 1.5 - 0.2  # float TIFF is linear, unclipped
        expected = data.astype(np.float64)
    else:
        top = np.iinfo(dtype).max
        data = rng.integers(0, top + 1, (9, 11, 3), dtype=dtype)
        expected = eotf(data, top)
    stored = np.moveaxis(data, -1, 0) if planar else data
    path = tmp_path / "img.tif"
    tifffile.imwrite(path, stored, photometric="rgb", planarconfig="separate" if planar else None)
    image = read_frame(path)
    assert image.shape == (9, 11, 3) and image.dtype == np.float32
    np.testing.assert_allclose(image, expected, rtol=1e-6, atol=1e-9)
    assert frame_info(path).shape == (9, 11, 3)


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize(
    ("codec", "dtype"),
    [
        (5, np.uint8),  # LZW: what Photoshop, Lightroom and OpenCV write by default
        (5, np.uint16),
        (5, np.float32),
        (32946, np.uint16),  # Deflate, which tifffile decodes itself
        (32946, np.float32),  # libtiff adds the floating-point predictor tifffile lacks
    ],
)
def test_compressed_tiff_written_by_libtiff(tmp_path, codec, dtype, channels):
    """Bytes from libtiff (through OpenCV's writer) decode to the stored samples, in RGB."""
    rng = np.random.default_rng(5)
    shape = (9, 11, channels) if channels == 3 else (9, 11)
    if np.dtype(dtype).kind == "f":
        data = rng.random(shape).astype(dtype) * 1.5 - 0.2
        expected = data.astype(np.float64)
    else:
        top = np.iinfo(dtype).max
        data = rng.integers(0, top + 1, shape, dtype=dtype)
        expected = eotf(data, top)
    path = tmp_path / "img.tif"
    stored = data[..., ::-1] if channels == 3 else data  # OpenCV writes BGR
    assert cv2.imwrite(str(path), stored, [cv2.IMWRITE_TIFF_COMPRESSION, codec])
    with tifffile.TiffFile(path) as tif:
        assert int(tif.pages.first.compression) == codec
    image = read_frame(path)
    assert image.shape == shape and image.dtype == np.float32
    np.testing.assert_allclose(image, expected, rtol=1e-6, atol=1e-9)


def test_jpeg_compressed_tiff_keeps_its_colours(tmp_path):
    rows, cols = np.mgrid[0:32, 0:48]
    rgb = np.stack([rows * 7, np.full_like(rows, 128), 255 - cols * 5], -1).astype(np.uint8)
    path = tmp_path / "img.tif"
    assert cv2.imwrite(str(path), rgb[..., ::-1], [cv2.IMWRITE_TIFF_COMPRESSION, 7])
    codes = np.rint(linear_to_srgb(read_frame(path)) * 255)
    assert np.abs(codes - rgb).mean() < 3  # lossy, but red stays red and blue blue


@pytest.mark.parametrize("opaque", [True, False])
def test_lzw_tiff_with_alpha(tmp_path, opaque):
    """libtiff's RGBA path (OpenCV) multiplies colour by an unassociated alpha."""
    rng = np.random.default_rng(6)
    rgb = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    alpha = np.full((12, 16, 1), 255, np.uint8) if opaque else rng.integers(1, 256, (12, 16, 1))
    path = tmp_path / "rgba.tif"
    Image.fromarray(np.dstack([rgb, alpha.astype(np.uint8)]), "RGBA").save(
        path, compression="tiff_lzw"
    )
    if opaque:
        np.testing.assert_allclose(read_frame(path), eotf(rgb, 255), rtol=1e-6, atol=1e-9)
    else:
        with pytest.raises(InputError, match=r"rgba\.tif: its alpha channel is not opaque"):
            read_frame(path)


def test_lzw_tiff_of_16_bit_rgba_reads_as_stored(tmp_path):
    """OpenCV reads 16-bit RGBA as stored (only 8-bit goes through libtiff's RGBA path)."""
    rgba = np.random.default_rng(7).integers(1, 65536, (12, 16, 4), dtype=np.uint16)
    path = tmp_path / "rgba16.tif"
    assert cv2.imwrite(str(path), rgba)  # LZW, alpha not opaque
    expected = eotf(rgba[..., 2::-1], 65535)  # the stored RGB
    np.testing.assert_allclose(read_frame(path), expected, rtol=1e-6, atol=1e-9)


def test_tiff_with_a_codec_nothing_here_decodes(tmp_path):
    path = tmp_path / "webp.tif"
    tifffile.imwrite(path, np.zeros((8, 8, 3), np.uint8), photometric="rgb")
    with tifffile.TiffFile(path, mode="r+b") as tif:
        tif.pages.first.tags["Compression"].overwrite(50001)  # WebP: needs imagecodecs
    with pytest.raises(InputError, match=r"webp\.tif: cannot decode its WEBP.*imagecodecs"):
        read_frame(path)


def test_tiff_transfer_override(tmp_path):
    codes = np.arange(0, 65536, 257, dtype=np.uint16).reshape(16, 16)
    tifffile.imwrite(tmp_path / "lin.tif", codes)
    np.testing.assert_allclose(read_frame(tmp_path / "lin.tif", transfer="linear"), codes / 65535)
    with pytest.raises(InputError, match="transfer"):
        read_frame(tmp_path / "lin.tif", transfer="gamma")


# --- writing ---------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(13, 19), (13, 19, 3)])
@pytest.mark.parametrize(
    ("name", "encoding", "bits"),
    [("a.png", None, 8), ("a.png", "srgb16", 16), ("a.tif", None, 16), ("a.tif", "srgb8", 8)],
)
def test_srgb_integer_round_trip(tmp_path, shape, name, encoding, bits):
    image = ramp(shape, np.random.default_rng(3))
    path = tmp_path / name
    write_image(path, image, encoding=encoding)
    back = read_frame(path)
    assert back.shape == shape and back.dtype == np.float32
    # Quantisation happens in the encoded domain: within half a code step there.
    step = 1 / (2**bits - 1)
    encoded = 1.055 * np.maximum(image.astype(np.float64), 0.0031308) ** (1 / 2.4) - 0.055
    encoded = np.where(image <= 0.0031308, 12.92 * image, encoded)
    assert np.max(np.abs(linear_to_srgb(back.astype(np.float64)) - encoded)) <= step / 2 + 1e-6


def test_written_png_codes_are_srgb(tmp_path):
    """An independent reader (OpenCV) sees round(255 * sRGB(x)) codes."""
    image = np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8)
    write_image(tmp_path / "g.png", image)
    codes = cv2.imread(str(tmp_path / "g.png"), cv2.IMREAD_UNCHANGED)
    lin = image.astype(np.float64)
    srgb = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    np.testing.assert_array_equal(codes, np.rint(srgb * 255).astype(np.uint8))


@pytest.mark.parametrize("shape", [(13, 19), (13, 19, 3)])
def test_linear16_and_float32_tiff(tmp_path, shape):
    image = ramp(shape, np.random.default_rng(4))
    write_image(tmp_path / "l.tif", image, encoding="linear16")
    assert np.max(np.abs(read_frame(tmp_path / "l.tif") - image)) <= 0.5 / 65535 + 1e-7
    raw_codes = tifffile.imread(tmp_path / "l.tif")
    np.testing.assert_array_equal(raw_codes, np.rint(image.astype(np.float64) * 65535))
    wide = image * 3 - 1  # float32 is written unclipped, exactly
    write_image(tmp_path / "f.tif", wide, encoding="float32")
    back = read_frame(tmp_path / "f.tif")
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, wide)


def test_integer_encoding_clips(tmp_path):
    image = np.array([[-0.5, 0.0, 1.0, 2.0]], dtype=np.float32)
    write_image(tmp_path / "c.png", image)
    np.testing.assert_array_equal(
        cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED), [[0, 0, 255, 255]]
    )


def test_jpeg_round_trip(tmp_path):
    yy, xx = np.mgrid[0:64, 0:96]
    image = np.stack([xx / 95, yy / 63, (xx + yy) / 158], axis=-1).astype(np.float32) ** 2
    write_image(tmp_path / "s.jpg", image)
    back = read_frame(tmp_path / "s.jpg")
    assert back.shape == image.shape
    # JPEG q95 on a smooth image: small error in the encoded domain.
    err = np.abs(linear_to_srgb(back) - linear_to_srgb(image))
    assert err.mean() < 0.01 and err.max() < 0.06


@pytest.mark.parametrize("ext", [".jpg", ".png"])
def test_exif_is_carried(tmp_path, shared_data, ext):
    source = shared_data / "focusstack-pcb" / "pcb7" / "pcb_001.jpg"
    exif = read_exif(source)
    assert exif is not None and exif.startswith(b"Exif\x00\x00")
    out = tmp_path / f"o{ext}"
    write_image(out, np.full((8, 8, 3), 0.5, np.float32), exif=exif)
    assert read_exif(out) == exif
    with Image.open(source) as src, Image.open(out) as dst:  # an independent EXIF parser
        assert dst.getexif()[0x0110] == src.getexif()[0x0110]  # camera model
    assert read_frame(out).shape == (8, 8, 3)


def test_subject_distance(tmp_path, shared_data):
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0x9206] = IFDRational(1234, 1000)  # 1.234 m
    write_image(tmp_path / "d.jpg", np.zeros((8, 8), np.float32), exif=exif.tobytes())
    assert subject_distance_mm(tmp_path / "d.jpg") == pytest.approx(1234.0)
    exif.get_ifd(0x8769)[0x9206] = IFDRational(0xFFFFFFFF, 1)
    write_image(tmp_path / "i.jpg", np.zeros((8, 8), np.float32), exif=exif.tobytes())
    assert subject_distance_mm(tmp_path / "i.jpg") == math.inf
    # pcb has no SubjectDistance; the beetle's is 0 ("unknown"); the DNG has none.
    assert subject_distance_mm(shared_data / "focusstack-pcb" / "pcb7" / "pcb_001.jpg") is None
    assert subject_distance_mm(shared_data / "chimpstackr-beetle" / "DSC_0356.jpg") is None
    assert subject_distance_mm(shared_data / "raw-dng-canon550d" / "colorchart.dng") is None


@settings(max_examples=40, deadline=None)
@given(
    numerator=st.integers(0, 0xFFFFFFFF),
    denominator=st.integers(1, 0xFFFFFFFF),
    other_tags=st.integers(0, 6),
    big_endian=st.booleans(),
)
def test_subject_distance_reader_agrees_with_pillow(
    tmp_path_factory, numerator, denominator, other_tags, big_endian
):
    """The EXIF walk reads what pillow (an independent writer and parser) put there, among
    other tags of both IFDs, in either byte order; pillow's own reading is the reference."""
    exif = Image.Exif()
    exif.endian = ">" if big_endian else "<"
    for i in range(other_tags):
        # IFD0 text tags (description, make, model, software, artist, copyright): the
        # Exif IFD pointer is not the first entry, nor the last
        exif[(0x010E, 0x010F, 0x0110, 0x0131, 0x013B, 0x8298)[i]] = f"tag {i}"
        exif.get_ifd(0x8769)[0x9000 + i] = IFDRational(i + 1, 3)
    exif.get_ifd(0x8769)[0x9206] = IFDRational(numerator, denominator)
    block = exif.tobytes()
    assert block[6:8] == (b"MM" if big_endian else b"II")
    out = tmp_path_factory.mktemp("exif") / "d.jpg"
    write_image(out, np.zeros((4, 4), np.float32), exif=block)
    reference = Image.Exif()
    reference.load(read_exif(out))
    value = reference.get_ifd(0x8769)[0x9206]
    expected = (
        math.inf
        if value.numerator == 0xFFFFFFFF
        else None
        if value.numerator == 0
        else value.numerator / value.denominator * 1e3
    )
    got = subject_distance_mm(out)
    assert got == (
        pytest.approx(expected, rel=1e-12) if expected not in (None, math.inf) else expected
    )


def test_subject_distance_of_malformed_exif_blocks_is_absent(tmp_path):
    """Truncated or foreign blocks, a pointer past the end, a SubjectDistance of the wrong
    type: no value and no exception (the frame still loads, positions come from elsewhere)."""
    exif = Image.Exif()
    exif.get_ifd(0x8769)[0x9206] = IFDRational(1234, 1000)
    good = exif.tobytes()
    wrong_type = Image.Exif()
    wrong_type.get_ifd(0x8769)[0x9206] = 7  # a SHORT, not a RATIONAL
    blocks = [
        good[:12],
        good[:-4],
        b"Exif\x00\x00XX*\x00\x08\x00\x00\x00",
        good[:10] + b"\xff\xff\xff\x00" + good[14:],
        wrong_type.tobytes(),
    ]
    for i, block in enumerate(blocks):
        out = tmp_path / f"m{i}.jpg"
        write_image(out, np.zeros((4, 4), np.float32), exif=block)
        assert subject_distance_mm(out) is None, i
    write_image(tmp_path / "g.jpg", np.zeros((4, 4), np.float32), exif=good)
    assert subject_distance_mm(tmp_path / "g.jpg") == pytest.approx(1234.0)


def test_write_json(tmp_path):
    write_json(tmp_path / "r.json", {"a": np.float32(0.5), "h": np.eye(2), "p": tmp_path})
    assert (tmp_path / "r.json").read_text().startswith("{\n")
    with pytest.raises(InputError, match="JSON"):
        write_json(tmp_path / "bad.json", {"x": float("nan")})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


# --- atomic writes and refusals -------------------------------------------------------------


def test_write_onto_directory_leaves_nothing(tmp_path):
    target = tmp_path / "out.png"
    target.mkdir()
    with pytest.raises(InputError, match=r"out\.png"):
        write_image(target, np.zeros((4, 4), np.float32))
    assert target.is_dir() and not any(target.iterdir())
    assert [p.name for p in tmp_path.iterdir()] == ["out.png"]  # no temporary file left


@pytest.mark.parametrize("name", ["out.png", "out.jpg", "out.tif"])
def test_failed_write_keeps_existing_file(tmp_path, name):
    target = tmp_path / name
    write_image(target, np.full((4, 4), 0.25, np.float32))
    before = target.read_bytes()
    bad = np.full((4, 4), 0.25, np.float32)
    bad[1, 2] = np.nan
    with pytest.raises(InputError, match="NaN"):
        write_image(target, bad)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [name]


def test_write_into_missing_directory(tmp_path):
    with pytest.raises(InputError, match="cannot write"):
        write_image(tmp_path / "nope" / "a.png", np.zeros((2, 2), np.float32))


@pytest.mark.parametrize(
    ("name", "image", "kwargs", "match"),
    [
        ("a.png", np.zeros((2, 2), np.uint8), {}, "float linear light"),
        ("a.png", np.zeros((2, 2, 2), np.float32), {}, "shape"),
        ("a.bmp", np.zeros((2, 2), np.float32), {}, "extension"),
        ("a.jpg", np.zeros((2, 2), np.float32), {"encoding": "srgb16"}, "encoding"),
        ("a.png", np.zeros((2, 2), np.float32), {"encoding": "float32"}, "encoding"),
    ],
)
def test_write_refusals(tmp_path, name, image, kwargs, match):
    with pytest.raises(InputError, match=match):
        write_image(tmp_path / name, image, **kwargs)
    assert not any(tmp_path.iterdir())


# --- bad input files -------------------------------------------------------------------------


def cut(src, dst, fraction):
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * fraction)])
    return dst


@pytest.mark.parametrize("fraction", [0.05, 0.6, 0.99])
def test_truncated_jpeg(tmp_path, shared_data, fraction):
    bad = cut(shared_data / "focusstack-pcb" / "pcb7" / "pcb_003.jpg", tmp_path / "t.jpg", fraction)
    for func in (read_frame, frame_info):
        with pytest.raises(InputError, match=r"t\.jpg: truncated"):
            func(bad)


@pytest.mark.parametrize("fraction", [0.001, 0.5, 0.99])
def test_truncated_dng(tmp_path, shared_data, fraction, capfd):
    bad = cut(shared_data / "raw-dng-canon550d" / "colorchart.dng", tmp_path / "t.dng", fraction)
    with pytest.raises(InputError, match=r"t\.dng: LibRaw cannot decode it.*truncated"):
        read_frame(bad)
    capfd.readouterr()  # LibRaw reports "Unexpected end of file" on stderr itself


def test_truncated_png(tmp_path):
    write_image(tmp_path / "ok.png", np.zeros((40, 40, 3), np.float32))
    bad = cut(tmp_path / "ok.png", tmp_path / "t.png", 0.8)
    with pytest.raises(InputError, match=r"t\.png: truncated PNG"):
        read_frame(bad)


@pytest.mark.parametrize("fraction", [0.3, 0.95])
@pytest.mark.parametrize("writer", ["tifffile", "libtiff"])
def test_truncated_tiff(tmp_path, writer, fraction):
    """libtiff (OpenCV, Photoshop) writes the image directory after the pixels, so a
    file cut short has none: tifffile raised IndexError, a traceback in the CLI."""
    image = np.random.default_rng(3).integers(0, 65535, (60, 80, 3), dtype=np.uint16)
    whole = tmp_path / "whole.tif"
    if writer == "tifffile":
        tifffile.imwrite(whole, image, photometric="rgb")
    else:
        assert cv2.imwrite(str(whole), image)  # LZW, directory last
    bad = cut(whole, tmp_path / "t.tif", fraction)
    for func in (read_frame, frame_info):
        with pytest.raises(InputError, match=r"t\.tif: truncated TIFF.*copy it again"):
            func(bad)
    assert exif_orientation(bad) == 1 and read_icc(bad) is None  # read_frame names the fault
    assert subject_distance_mm(bad) is None


def test_a_frame_cut_short_is_one_line_in_the_cli(tmp_path, capsys):
    from pipeline.cli import main

    rng = np.random.default_rng(4)
    for i in range(3):
        frame = rng.integers(0, 65535, (64, 96, 3), dtype=np.uint16)
        assert cv2.imwrite(str(tmp_path / f"f{i}.tif"), frame)
    cut(tmp_path / "f1.tif", tmp_path / "f1.tif", 0.5)
    assert main(["stack", str(tmp_path), "-o", str(tmp_path / "out.tif")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "f1.tif: truncated TIFF" in err, err
    assert not (tmp_path / "out.tif").exists()


@pytest.mark.parametrize("name", ["x.jpg", "x.png", "x.tif", "x.dng", "x.nef"])
def test_not_an_image(tmp_path, name, capfd):
    (tmp_path / name).write_bytes(b"this is not an image at all" * 10)
    with pytest.raises(InputError, match=rf"{name.replace('.', '[.]')}"):
        read_frame(tmp_path / name)
    capfd.readouterr()


def test_missing_and_unsupported(tmp_path):
    with pytest.raises(InputError, match="no such image file"):
        read_frame(tmp_path / "missing.jpg")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(InputError, match="unsupported image extension"):
        read_frame(tmp_path / "notes.txt")


# --- real data -------------------------------------------------------------------------------


def test_pcb_jpeg(shared_data):
    path = shared_data / "focusstack-pcb" / "pcb7" / "pcb_001.jpg"
    image = read_frame(path)
    assert image.shape == (1536, 2048, 3) and image.dtype == np.float32
    assert frame_info(path).shape == image.shape
    codes = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[:, :, ::-1]
    np.testing.assert_allclose(image, eotf(codes, 255), rtol=1e-6, atol=1e-9)


def test_kdc_decodes(shared_data):
    path = shared_data / "raw-kdc-kodak-dc50" / "RAW_KODAK_DC50.KDC"
    image = read_frame(path)
    assert image.shape == (512, 768, 3) and image.dtype == np.float32
    assert frame_info(path).shape == image.shape
    assert 0.0 <= image.min() and image.max() <= 1.0 and 0.01 < image.mean() < 0.9


# ColorChecker patches in colorchart.dng (row, col centres of the 6x4 lower chart).
PATCH_ROWS = (624, 720, 820, 926)
PATCH_COLS = (710, 820, 930, 1034, 1144, 1250)
HALF = 16


def patch_means(shared_data):
    """Per patch: black-subtracted, white-normalised raw means per CFA colour and decoded means."""
    path = shared_data / "raw-dng-canon550d" / "colorchart.dng"
    decoded = read_frame(path)
    with rawpy.imread(str(path)) as raw:
        mosaic = raw.raw_image_visible.astype(np.float64)
        colours = raw.raw_colors_visible.copy()
        black = np.array(raw.black_level_per_channel, dtype=np.float64)
        white = float(raw.white_level)
    assert decoded.shape[:2] == mosaic.shape  # flip 0: same pixel grid
    raw_means, dec_means = [], []
    for r in PATCH_ROWS:
        for c in PATCH_COLS:
            win = (slice(r - HALF, r + HALF), slice(c - HALF, c + HALF))
            m, k = mosaic[win], colours[win]
            norm = [(m[k == i] - black[i]).mean() / (white - black[i]) for i in range(4)]
            raw_means.append([norm[0], (norm[1] + norm[3]) / 2, norm[2]])  # R, G (2 sites), B
            dec_means.append(decoded[win].reshape(-1, 3).mean(axis=0))
    return np.array(raw_means), np.array(dec_means, dtype=np.float64)


def linear_fit_residual(raw_means, values):
    """Max residual of the best fit ``values = raw_means @ M`` (3x3, no offset), relative."""
    m, *_ = np.linalg.lstsq(raw_means, values, rcond=None)
    return np.max(np.abs(raw_means @ m - values)) / np.max(values)


def test_dng_is_linear_in_raw_values(shared_data):
    raw_means, dec = patch_means(shared_data)
    # Grey row (last 6 patches): decoded green / raw green is one constant (no gamma, no curve).
    ratio = dec[18:, 1] / raw_means[18:, 1]
    assert ratio.max() / ratio.min() < 1.06
    # All 24 patches: decoded RGB is a linear map (the colour matrix x white balance) of raw RGB.
    assert linear_fit_residual(raw_means, dec) < 0.01
    # The same checks fail for gamma-encoded data, so they do detect a curve.
    gamma = dec ** (1 / 2.2)
    g_ratio = gamma[18:, 1] / raw_means[18:, 1]
    assert g_ratio.max() / g_ratio.min() > 2
    assert linear_fit_residual(raw_means, gamma) > 0.1


def test_dng_normalised_by_black_and_white(shared_data):
    """Green has white-balance gain 1: grey-patch green ~ (raw - black) / (white - black)."""
    raw_means, dec = patch_means(shared_data)
    ratio = dec[18:, 1] / raw_means[18:, 1]
    assert 0.9 < np.median(ratio) < 1.1
    path = shared_data / "raw-dng-canon550d" / "colorchart.dng"
    assert frame_info(path).shape == (1156, 1734, 3)


def test_no_stray_files_in_cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    write_image("rel.png", np.zeros((2, 2), np.float32))
    assert sorted(os.listdir(tmp_path)) == ["rel.png"]


def test_a_white_level_divides_float_tiffs_and_is_refused_for_codes(tmp_path):
    """``white``: float TIFF samples in other units, divided by it; integer codes (whose
    white is their largest code) and RAW files refuse it, naming the file."""
    image = np.array([[0.0, 1000.0, 4095.0, 8190.0]], dtype=np.float32)
    write_image(tmp_path / "counts.tif", image, encoding="float32")
    back = read_frame(tmp_path / "counts.tif", white=4095.0)
    np.testing.assert_allclose(back, [[0.0, 1000 / 4095, 1.0, 2.0]], rtol=1e-6)
    assert read_frame(tmp_path / "counts.tif")[0, 2] == 4095.0  # without it: as written
    from pipeline.io.read import read_preview

    np.testing.assert_allclose(read_preview(tmp_path / "counts.tif", 4, white=4095.0), back)
    write_image(tmp_path / "codes.tif", back / 2, encoding="srgb16")
    write_image(tmp_path / "codes.png", back / 2)
    for name, what in (("codes.tif", "16-bit codes"), ("codes.png", "PNG file")):
        with pytest.raises(InputError, match=rf"{name}: a white level .* {what}"):
            read_frame(tmp_path / name, white=2.0)
    with pytest.raises(InputError, match="PNG file"):
        read_preview(tmp_path / "codes.png", 2, white=2.0)
    for bad in (0.0, -1.0, math.inf, math.nan):
        with pytest.raises(InputError, match="white must be a finite number > 0"):
            read_frame(tmp_path / "counts.tif", white=bad)


@pytest.mark.parametrize("side", [768, 320])
def test_raw_previews_come_from_a_half_size_decode(shared_data, side, monkeypatch):
    """A RAW preview at most half the frame comes from LibRaw's half-size decode (each 2x2
    Bayer block one pixel): the same light and geometry as the full decode reduced (the
    real 550D DNG: means within 0.02%, 0.6-1.4% apart per pixel, 0.03-0.08 px apart), and the
    full decode is not run. A white level is refused as for read_frame."""
    from pipeline.io import read

    path = shared_data / "raw-dng-canon550d" / "colorchart.dng"
    full = read.read_frame(path).mean(axis=2)
    calls = []
    monkeypatch.setattr(read, "read_frame", lambda *a, **k: calls.append(a) or full)
    preview = read.read_preview(path, side)
    assert not calls  # the half-size decode, not the full one
    reduced = cv2.resize(full, preview.shape[::-1], interpolation=cv2.INTER_AREA)
    assert abs(float(preview.mean() / reduced.mean()) - 1) < 2e-3
    assert float(np.mean(np.abs(preview - reduced)) / reduced.mean()) < 0.03
    (dx, dy), _ = cv2.phaseCorrelate(reduced.astype(np.float64), preview.astype(np.float64))
    assert np.hypot(dx, dy) < 0.15
    monkeypatch.undo()
    with pytest.raises(InputError, match=r"colorchart\.dng: a white level"):
        read.read_preview(path, side, white=2.0)


def test_exif_too_large_for_a_jpeg_is_left_out_of_it_not_the_result(
    tmp_path, shared_data, caplog
):
    """PNG frames whose eXIf holds 85 kB (a 70 kB description): a JPEG's APP1 holds 64 kB.
    The job's JPEG is written without it and says so; its PNG carries it."""
    from pipeline.jobs.options import StackOptions
    from pipeline.jobs.stack import process_stack

    for src in sorted((shared_data / "chimpstackr-beetle").glob("*.jpg"))[:3]:
        with Image.open(src) as image:
            exif = image.getexif()
            exif[0x010E] = "x" * 70_000
            image.save(tmp_path / f"{src.stem}.png", exif=exif.tobytes())
    frames = sorted(tmp_path.glob("*.png"))
    with caplog.at_level("WARNING"):
        process_stack(frames, tmp_path / "out.jpg", StackOptions())
    assert "does not fit a JPEG's 64 kB APP1" in caplog.text
    assert read_exif(tmp_path / "out.jpg") is None
    process_stack(frames, tmp_path / "out.png", StackOptions())
    with Image.open(tmp_path / "out.png") as out:
        assert out.getexif()[0x010E] == "x" * 70_000
