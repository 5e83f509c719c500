"""pipeline.io.stackfile: loading stacks, stack.toml validation, frame checks, lazy reading."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from pipeline.errors import InputError
from pipeline.io.profiles import load_lens
from pipeline.io.stackfile import (
    Frame,
    check_frames,
    image_distances_mm,
    load_stack,
    natural_key,
    sweep_profile,
)
from pipeline.io.write import write_image

LENS = "fujinon-12.5mm-f1.4-sony-1-3in"  # f = 12.5 mm


def thin_lens_v(f, u):
    """Image distance of Eq. 1 written out here: 1/f = 1/u + 1/v."""
    return f if math.isinf(u) else 1.0 / (1.0 / f - 1.0 / u)


def make_frames(directory, names, shape=(6, 8)):
    directory.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        write_image(directory / name, np.full(shape, i / 10, np.float32))
    return directory


def write_toml(directory, text):
    (directory / "stack.toml").write_text(text)
    return directory


# --- file discovery --------------------------------------------------------------------------


def test_natural_key_orders_numbers():
    names = ["pcb_10.png", "pcb_2.png", "pcb_1.png", "Pcb_3.png"]
    assert sorted(names, key=natural_key) == ["pcb_1.png", "pcb_2.png", "Pcb_3.png", "pcb_10.png"]


def test_directory_without_sidecar(tmp_path):
    make_frames(tmp_path, ["f_10.png", "f_2.png", "f_1.tif"])
    (tmp_path / "notes.txt").write_text("not an image")
    stack = load_stack(tmp_path)
    assert [f.file.name for f in stack.frames] == ["f_1.tif", "f_2.png", "f_10.png"]
    assert stack.kind == "focal-stack" and stack.lens is None and not stack.partial
    assert image_distances_mm(stack) is None and stack.positions_source is None


@pytest.mark.parametrize("content", [None, "notes.txt"])
def test_empty_directory(tmp_path, content):
    if content:
        (tmp_path / content).write_text("x")
    with pytest.raises(InputError, match=rf"no image files in {tmp_path}; supported: .*\.jpg"):
        load_stack([tmp_path])


def test_pcb7_glob_and_directory(shared_data):
    folder = shared_data / "focusstack-pcb" / "pcb7"
    stack = load_stack([str(folder / "pcb_*.jpg")])
    assert [f.file.name for f in stack.frames] == [f"pcb_{i:03d}.jpg" for i in range(1, 8)]
    # A directory means every frame in it: the reference output expected.jpg is skipped
    # (with a warning; tests/test_ingestion.py).
    assert [f.file.name for f in load_stack(folder).frames] == [
        f"pcb_{i:03d}.jpg" for i in range(1, 8)
    ]


def test_files_and_globs(tmp_path):
    make_frames(tmp_path, ["a_1.png", "a_2.png", "b_1.png"])
    stack = load_stack([tmp_path / "b_1.png", str(tmp_path / "a_*.png")])
    assert [f.file.name for f in stack.frames] == ["b_1.png", "a_1.png", "a_2.png"]
    with pytest.raises(InputError, match="listed twice"):
        load_stack([tmp_path / "a_1.png", str(tmp_path / "a_*.png")])
    with pytest.raises(InputError, match="no such file"):
        load_stack([tmp_path / "missing.png"])
    with pytest.raises(InputError, match="matches no image files"):
        load_stack([str(tmp_path / "z_*.png")])
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(InputError, match="not a supported image extension"):
        load_stack([tmp_path / "x.txt"])
    with pytest.raises(InputError, match="directory"):
        load_stack([tmp_path, tmp_path / "a_1.png"])
    with pytest.raises(InputError, match="no input"):
        load_stack([])


def test_exif_subject_distance_without_sidecar(tmp_path):
    for i, metres in enumerate((0.5, 1.0, math.inf)):
        exif = Image.Exif()
        num = 0xFFFFFFFF if math.isinf(metres) else int(metres * 1000)
        exif.get_ifd(0x8769)[0x9206] = IFDRational(num, 1 if math.isinf(metres) else 1000)
        write_image(tmp_path / f"e_{i}.jpg", np.zeros((4, 4), np.float32), exif=exif.tobytes())
    stack = load_stack(tmp_path)
    assert stack.positions_source == "exif"
    assert [f.focus_distance_mm for f in stack.frames] == [500.0, 1000.0, math.inf]
    lens = load_lens(LENS)
    got = image_distances_mm(stack, lens)
    expected = [thin_lens_v(12.5, u) for u in (500.0, 1000.0, math.inf)]
    np.testing.assert_allclose(got.image_distances_mm, expected, rtol=1e-12)
    assert not got.relative


# --- stack.toml ------------------------------------------------------------------------------


def test_sidecar_focus_and_image_distances(tmp_path):
    make_frames(tmp_path, ["f_1.png", "f_2.png", "f_10.png"])
    write_toml(
        tmp_path,
        f"""
lens = "{LENS}"
kind = "focal-stack"
[[frames]]
file = "f_10.png"
focus_distance_mm = inf
[[frames]]
file = "f_1.png"
focus_distance_mm = 450.0
[[frames]]
file = "f_2.png"
image_distance_mm = 12.7
""",
    )
    stack = load_stack(tmp_path)
    assert [f.file.name for f in stack.frames] == ["f_1.png", "f_2.png", "f_10.png"]
    assert stack.lens == LENS and stack.lens_profile.focal_length_mm == 12.5
    assert stack.positions_source == "stack.toml"
    positions = image_distances_mm(stack)
    np.testing.assert_allclose(
        positions.image_distances_mm, [thin_lens_v(12.5, 450.0), 12.7, 12.5], rtol=1e-12
    )
    assert not positions.relative
    assert load_stack(tmp_path / "stack.toml").frames == stack.frames


def test_sidecar_lens_path_relative_to_stack(tmp_path):
    (tmp_path / "mylens.toml").write_text(
        "focal_length_mm = 50.0\nf_number = 2.0\n"
        "[sensor]\npixel_pitch_um = 5.0\nwidth_px = 100\nheight_px = 80\n"
        "[focus]\nstep_image_distance_um = 2.5\n"
    )
    make_frames(tmp_path, ["a.png", "b.png", "c.png"])
    write_toml(
        tmp_path,
        """
lens = "mylens.toml"
[[frames]]
file = "a.png"
focus_step = 100
[[frames]]
file = "b.png"
focus_step = 110
[[frames]]
file = "c.png"
focus_step = 90
""",
    )
    stack = load_stack(tmp_path)
    positions = image_distances_mm(stack)
    assert positions.relative
    np.testing.assert_allclose(positions.image_distances_mm, [0.0, 0.025, -0.025])


def test_focus_step_needs_calibrated_lens(tmp_path):
    make_frames(tmp_path, ["a.png"])
    write_toml(tmp_path, f'lens = "{LENS}"\n[[frames]]\nfile = "a.png"\nfocus_step = 3\n')
    stack = load_stack(tmp_path)
    with pytest.raises(InputError, match="step_image_distance_um"):
        image_distances_mm(stack)


def test_focus_distance_without_lens(tmp_path):
    make_frames(tmp_path, ["a.png"])
    write_toml(tmp_path, '[[frames]]\nfile = "a.png"\nfocus_distance_mm = 300\n')
    stack = load_stack(tmp_path)
    with pytest.raises(InputError, match="lens"):
        image_distances_mm(stack)
    v = image_distances_mm(stack, load_lens(LENS)).image_distances_mm
    np.testing.assert_allclose(v, [thin_lens_v(12.5, 300.0)], rtol=1e-12)


def test_partial_is_accepted_with_warning(tmp_path, caplog):
    make_frames(tmp_path, ["a.png"])
    write_toml(tmp_path, 'partial = true\n[[frames]]\nfile = "a.png"\n')
    with caplog.at_level(logging.WARNING, logger="pipeline.io.stackfile"):
        stack = load_stack(tmp_path)
    assert stack.partial
    assert "partial" in caplog.text and "interrupted" in caplog.text


BAD_SIDECARS = [
    ('[[frames]]\nfile = "missing.png"\n', r"stack\.toml: 'file' in \[\[frames\]\] #1: .*missing"),
    (
        '[[frames]]\nfile = "a.png"\nfocus_distance_mm = 400\nimage_distance_mm = 12.9\n',
        "focus_distance_mm and image_distance_mm; give exactly one",
    ),
    (
        f'lens = "{LENS}"\n[[frames]]\nfile = "a.png"\nfocus_distance_mm = 12.5\n',
        "focus_distance_mm = 12.5 of a.png must exceed the focal length 12.5 mm",
    ),
    (
        f'lens = "{LENS}"\n[[frames]]\nfile = "a.png"\nimage_distance_mm = 12.0\n',
        "image_distance_mm = 12.0 of a.png is less than the focal length",
    ),
    ('lens = "no-such-lens"\n[[frames]]\nfile = "a.png"\n', "lens = 'no-such-lens': unknown lens"),
    ('lense = "x"\n[[frames]]\nfile = "a.png"\n', "unknown key 'lense'"),
    ('[[frames]]\nfile = "a.png"\nfocus = 3\n', r"unknown key 'focus' in \[\[frames\]\] #1"),
    ('[[frames]]\nfile = "a.png"\n[[frames]]\nfile = "./a.png"\n', "listed twice"),
    ('[[frames]]\nfile = "a.png"\nfocus_distance_mm = -4\n', "must be > 0, got -4"),
    ('[[frames]]\nfile = "a.png"\nfocus_distance_mm = "far"\n', "must be a number"),
    ('[[frames]]\nfile = "a.png"\nimage_distance_mm = inf\n', "finite"),
    ('kind = "burst"\n[[frames]]\nfile = "a.png"\n', "kind must be one of"),
    ('partial = "yes"\n[[frames]]\nfile = "a.png"\n', "partial must be true or false"),
    ("kind = 'focal-stack'\n", r"at least one \[\[frames\]\]"),
    ('[[frames]]\nfile = "a.png"\nfocus_step = 1\n[[frames]]\nfile = "b.png"\n', "no focus pos"),
    (
        '[[frames]]\nfile = "a.png"\nfocus_step = 1\n'
        '[[frames]]\nfile = "b.png"\nimage_distance_mm = 13\n',
        "cannot be mixed",
    ),
    ('[[frames]]\nfile = "notes.txt"\n', "not a supported image"),
    ("this is = not toml [", "cannot read it as TOML"),
    ('kind = "sweep"\n', r"needs a \[sweep\] table"),
    (
        'kind = "sweep"\n[sweep]\nfile = "a.png"\nexposure_s = 0.3\n'
        "start_image_distance_mm = 12.6\n",
        "exactly one pair of ends",
    ),
    (
        'kind = "sweep"\n[sweep]\nfile = "a.png"\nexposure_s = 0.3\nstart_image_distance_mm = 12.6'
        "\nend_image_distance_mm = 12.9\nspeed = 1\n",
        r"unknown key 'speed' in \[sweep\]",
    ),
    (
        'kind = "sweep"\n[sweep]\nfile = "a.png"\nexposure_s = 0.3\nstart_image_distance_mm = 12.6'
        '\nend_image_distance_mm = 12.9\nprofile = "sine"\n',
        "profile in",
    ),
    ('[sweep]\nfile = "a.png"\n', "needs kind = 'sweep'"),
]


@pytest.mark.parametrize(("text", "match"), BAD_SIDECARS)
def test_bad_sidecar(tmp_path, text, match):
    make_frames(tmp_path, ["a.png", "b.png"])
    (tmp_path / "notes.txt").write_text("x")
    write_toml(tmp_path, text)
    with pytest.raises(InputError, match=match) as info:
        load_stack(tmp_path)
    assert str(tmp_path / "stack.toml") in str(info.value)


def test_frame_rejects_two_positions(tmp_path):
    with pytest.raises(InputError, match="exactly one"):
        Frame(tmp_path / "a.png", focus_distance_mm=400.0, focus_step=3)


# --- sweep captures --------------------------------------------------------------------------


def test_sweep_with_image_distances(tmp_path):
    make_frames(tmp_path, ["capture.png"])
    write_toml(
        tmp_path,
        """
kind = "sweep"
[sweep]
file = "capture.png"
start_image_distance_mm = 12.5
end_image_distance_mm = 12.86
exposure_s = 0.36
profile = "constant-speed"
""",
    )
    stack = load_stack(tmp_path)
    assert stack.kind == "sweep" and [f.file.name for f in stack.frames] == ["capture.png"]
    profile = sweep_profile(stack)
    assert profile.exposure_s == pytest.approx(0.36)
    assert (profile.start_mm, profile.end_mm) == (12.5, 12.86)
    assert profile.max_speed_mm_s == pytest.approx(1.0)  # 0.36 mm in 0.36 s


def test_sweep_with_focus_distances(tmp_path):
    make_frames(tmp_path, ["capture.png"])
    write_toml(
        tmp_path,
        f"""
lens = "{LENS}"
kind = "sweep"
[sweep]
file = "capture.png"
start_focus_distance_mm = inf
end_focus_distance_mm = 450
exposure_s = 0.5
""",
    )
    profile = sweep_profile(load_stack(tmp_path))
    assert profile.start_mm == pytest.approx(12.5)
    assert profile.end_mm == pytest.approx(thin_lens_v(12.5, 450.0), rel=1e-12)
    with pytest.raises(InputError, match="not a sweep"):
        sweep_profile(load_stack(tmp_path / "capture.png"))


# --- frame checks and lazy reading -----------------------------------------------------------


def test_frames_of_different_sizes(tmp_path):
    make_frames(tmp_path, ["a_1.png", "a_2.png"], shape=(6, 8))
    write_image(tmp_path / "a_3.png", np.zeros((6, 9), np.float32))
    stack = load_stack(tmp_path)
    with pytest.raises(InputError, match=r"a_3\.png: 9x6 px, 1 channel.*expect 8x6 px"):
        check_frames(stack)


def test_frames_of_different_channels(tmp_path):
    make_frames(tmp_path, ["a_1.png"], shape=(6, 8))
    write_image(tmp_path / "a_2.png", np.zeros((6, 8, 3), np.float32))
    with pytest.raises(InputError, match=r"a_2\.png: 8x6 px, 3 channel"):
        check_frames(load_stack(tmp_path))


def test_frames_with_a_truncated_file(tmp_path, shared_data):
    source = shared_data / "focusstack-pcb" / "pcb7"
    data = (source / "pcb_002.jpg").read_bytes()
    (tmp_path / "pcb_001.jpg").write_bytes((source / "pcb_001.jpg").read_bytes())
    (tmp_path / "pcb_002.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"pcb_002\.jpg: truncated JPEG"):
        check_frames(load_stack(tmp_path))


@pytest.mark.parametrize(
    ("value", "match"),
    [("4095", None), ("0", "white must be > 0"), ('"4095"', "white must be a number"),
     ("nan", "white must be a finite number")],
)
def test_white_in_stack_toml(tmp_path, value, match):
    make_frames(tmp_path, ["a.png", "b.png"])
    frames = '[[frames]]\nfile = "a.png"\n[[frames]]\nfile = "b.png"\n'
    write_toml(tmp_path, f"white = {value}\n" + frames)
    if match is None:
        assert load_stack(tmp_path).white == 4095.0
    else:
        with pytest.raises(InputError, match=rf"stack.toml: {match}"):
            load_stack(tmp_path)
