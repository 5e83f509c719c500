"""The area every aligned frame covers (``pipeline.core.common_area``) and ``--crop``.

Each test checks against an independent computation: a brute-force search of every
rectangle, frames' footprints found pixel by pixel by mapping back into each frame, and
pillow turning a mask as a viewer turns an EXIF-tagged frame.
"""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from PIL import Image

from pipeline.core.common_area import common_area, largest_rectangle
from pipeline.jobs.result import _common_box


def brute_force_largest(mask: np.ndarray) -> int:
    """The largest area of an all-ones rectangle, trying every rectangle."""
    rows, cols = mask.shape
    best = 0
    for r0 in range(rows):
        for r1 in range(r0 + 1, rows + 1):
            for c0 in range(cols):
                for c1 in range(c0 + 1, cols + 1):
                    if mask[r0:r1, c0:c1].all():
                        best = max(best, (r1 - r0) * (c1 - c0))
    return best


def turned_rectangle_mask(shape, centre, half, angle_deg) -> np.ndarray:
    """Cells whose centres lie inside a turned rectangle: a convex region."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    a = math.radians(angle_deg)
    u = (xx - centre[1]) * math.cos(a) + (yy - centre[0]) * math.sin(a)
    v = -(xx - centre[1]) * math.sin(a) + (yy - centre[0]) * math.cos(a)
    return (np.abs(u) <= half[1]) & (np.abs(v) <= half[0])


@given(
    cy=st.floats(3, 9), cx=st.floats(3, 11), hy=st.floats(1, 6), hx=st.floats(1, 8),
    angle=st.floats(-40, 40),
)  # fmt: skip
@example(cy=6.0, cx=7.0, hy=4.0, hx=6.0, angle=30.0)
@settings(max_examples=40, deadline=None)
def test_largest_rectangle_of_a_convex_region_is_the_brute_force_one(cy, cx, hy, hx, angle):
    mask = turned_rectangle_mask((12, 15), (cy, cx), (hy, hx), angle)
    found = largest_rectangle(mask)
    best = brute_force_largest(mask)
    if best == 0:
        assert found is None
        return
    r, c, h, w = found
    assert mask[r : r + h, c : c + w].all()
    assert h * w == best


def shift(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1]])


def turn_about_centre(shape, angle_deg: float, scale: float = 1.0, d=(0.0, 0.0)) -> np.ndarray:
    rows, cols = shape
    cx, cy = (cols - 1) / 2, (rows - 1) / 2
    a = math.radians(angle_deg)
    c, s = scale * math.cos(a), scale * math.sin(a)
    return np.array([[c, -s, cx - c * cx + s * cy + d[0]], [s, c, cy - s * cx - c * cy + d[1]],
                     [0, 0, 1.0]])  # fmt: skip


def covered_by_every_frame(homographies, shape) -> np.ndarray:
    """Pixel by pixel: the result pixels whose whole square maps back inside every frame."""
    rows, cols = shape
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    inside = np.ones(shape, bool)
    for h in homographies:
        back = np.linalg.inv(h)
        for dy, dx in ((-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5), (0.5, 0.5)):  # the corners
            p = back @ np.stack([(xx + dx).ravel(), (yy + dy).ravel(), np.ones(xx.size)])
            x, y = (p[:2] / p[2]).reshape(2, rows, cols)
            inside &= (x >= -0.5) & (x <= cols - 0.5) & (y >= -0.5) & (y <= rows - 0.5)
    return inside


def test_shifted_frames_share_the_overlap_of_their_shifts():
    shape = (300, 400)
    moves = [shift(0, 0), shift(12.0, -7.0), shift(-5.0, 20.0)]
    y, x, h, w = common_area(moves, shape)
    # the overlap of the shifts: x in [12, 400 - 5), y in [20, 300 - 7)
    assert (y, x) >= (20, 12) and y + h <= 293 and x + w <= 395
    cell = max(shape) / 512 * 2 + 1  # the grid's resolution, two cells and a pixel
    assert h >= 273 - 2 * cell and w >= 383 - 2 * cell


def test_identity_homographies_cover_the_whole_result():
    assert common_area([np.eye(3)] * 3, (120, 160)) == (0, 0, 120, 160)


@pytest.mark.parametrize("angle", [0.0, 1.5, -3.0])
def test_turned_and_scaled_frames_leave_no_pixel_uncovered_inside(angle):
    """Breathing (scales 0.98-1.02) and a hand's turn: every pixel of the rectangle is
    covered by every frame (mapped back into each, by an independent pixel test), and the
    rectangle holds most of what the pixel test covers."""
    shape = (240, 320)
    moves = [
        turn_about_centre(shape, 0.0, 0.98, (3.0, -2.0)),
        np.eye(3),
        turn_about_centre(shape, angle, 1.02, (-6.0, 4.0)),
    ]
    y, x, h, w = common_area(moves, shape)
    covered = covered_by_every_frame(moves, shape)
    assert covered[y : y + h, x : x + w].all()
    assert h * w >= 0.85 * brute_force_free_bound(covered)


def brute_force_free_bound(covered: np.ndarray) -> int:
    """The largest all-covered rectangle, on a 4x coarser grid (cells wholly covered)."""
    rows, cols = covered.shape
    coarse = covered[: rows - rows % 4, : cols - cols % 4].reshape(rows // 4, 4, cols // 4, 4)
    return 16 * brute_force_largest_fast(coarse.all(axis=(1, 3)))


def brute_force_largest_fast(mask: np.ndarray) -> int:
    """Every rectangle by its row range: the widest run of columns ones in all its rows."""
    best = 0
    rows = mask.shape[0]
    for r0 in range(rows):
        shared = np.ones(mask.shape[1], bool)
        for r1 in range(r0, rows):
            shared &= mask[r1]
            run = longest = 0
            for v in shared:
                run = run + 1 if v else 0
                longest = max(longest, run)
            best = max(best, longest * (r1 - r0 + 1))
    return best


def test_frames_that_share_nothing_have_no_common_area():
    assert common_area([np.eye(3), shift(500.0, 0.0)], (100, 200)) is None


@pytest.mark.parametrize("code", [1, 3, 6, 8])
def test_the_box_is_given_in_the_written_images_geometry(code):
    """The result is written upright (EXIF orientation); the box turns with it, as pillow
    turns a mask of it the way a viewer shows a frame with that tag."""
    shape = (90, 160)
    sidecar = {"frames": [{"homography": np.eye(3).tolist()},
                          {"homography": shift(9.0, -6.0).tolist()}]}  # fmt: skip
    y, x, h, w = common_area([np.eye(3), shift(9.0, -6.0)], shape)
    mask = np.zeros(shape, np.uint8)
    mask[y : y + h, x : x + w] = 255
    transpose = {1: None, 3: Image.Transpose.ROTATE_180, 6: Image.Transpose.ROTATE_270,
                 8: Image.Transpose.ROTATE_90}[code]  # fmt: skip
    image = Image.fromarray(mask)
    turned = np.asarray(image if transpose is None else image.transpose(transpose)) > 0
    rows, cols = np.nonzero(turned.any(axis=1))[0], np.nonzero(turned.any(axis=0))[0]
    expected = (rows[0], cols[0], rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1)
    assert _common_box(sidecar, shape, code) == expected


def _shifted_stack(folder, sharp, shifts):
    from test_engine import make_stack, positions_for

    from pipeline.core import align
    from pipeline.io.read import read_frame
    from pipeline.io.write import write_image

    folder.mkdir()
    make_stack(folder, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, len(shifts)))
    for path, (dx, dy) in zip(sorted(folder.glob("frame_*.tif")), shifts):
        frame = read_frame(path)
        write_image(path, align.warp(frame, shift(dx, dy), frame.shape), encoding="float32")


@pytest.fixture(scope="module")
def sharp():
    from skimage import data

    from pipeline.core.colour import srgb_to_linear

    return srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)


def test_crop_writes_the_common_area_and_the_default_warns_of_it(tmp_path, sharp, caplog):
    """Frames shifted by up to 24 px (of 256): the default keeps the reference's size,
    records the area every frame covers and warns; ``--crop`` writes just that area."""
    from pipeline.cli import main

    shifts = [(-24.0, 10.0), (-12.0, 5.0), (0.0, 0.0), (12.0, -5.0), (24.0, -10.0)]
    _shifted_stack(tmp_path / "stack", sharp, shifts)
    whole, cropped = tmp_path / "whole.tif", tmp_path / "cropped.tif"
    with caplog.at_level(logging.WARNING):
        assert main(["stack", str(tmp_path / "stack"), "-o", str(whole)]) == 0
    assert "pass --crop" in caplog.text
    side = json.loads(whole.with_name(whole.name + ".json").read_text())
    area = side["common_area"]
    assert side["cropped"] is False and area["fraction"] < 0.9
    homographies = [np.array(f["homography"]) for f in side["frames"]]
    covered = covered_by_every_frame(homographies, (256, 256))
    y, x, h, w = area["y"], area["x"], area["height"], area["width"]
    assert covered[y : y + h, x : x + w].all() and h * w > 0.8 * covered.sum()
    assert main(["-q", "stack", str(tmp_path / "stack"), "-o", str(cropped), "--crop"]) == 0
    from pipeline.io.read import read_frame

    full, part = read_frame(whole), read_frame(cropped)
    assert part.shape[:2] == (h, w)
    np.testing.assert_allclose(part, full[y : y + h, x : x + w], atol=2e-4)  # 16-bit codes
    assert json.loads(cropped.with_name(cropped.name + ".json").read_text())["cropped"] is True


def test_crop_of_frames_that_share_no_area_warns_and_writes_it_uncropped(tmp_path, caplog):
    """A result whose frames share no area (not reachable through the main job's
    plausibility checks, so written directly): ``--crop`` says so and writes the image."""
    from pipeline.jobs.options import StackOptions
    from pipeline.jobs.result import write_result

    image = np.full((40, 60, 3), 0.5, np.float32)
    frames = [{"homography": np.eye(3).tolist()}, {"homography": shift(500.0, 0.0).tolist()}]
    inputs = [tmp_path / "a.png", tmp_path / "b.png"]
    for path in inputs:
        Image.fromarray(np.zeros((40, 60, 3), np.uint8)).save(path)
    out = tmp_path / "out.tif"
    with caplog.at_level(logging.WARNING, logger="pipeline"):  # a CLI run may have set it
        result = write_result(out, image, None, {"frames": frames}, {}, 0.0,
                              StackOptions(crop=True), inputs)  # fmt: skip
    assert "share no area" in caplog.text
    assert result.image.shape == (40, 60, 3) and "common_area" not in result.sidecar
    assert out.exists() and out.with_name("out.tif.json").exists()
