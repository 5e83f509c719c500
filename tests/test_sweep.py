"""Focus-sweep captures (Sec. 4, 8): single images, sequences, EDOF video, sweep stack dirs."""

import json

import cv2
import numpy as np
import pytest
from scipy.signal import fftconvolve
from skimage import data

from pipeline.cli import main
from pipeline.core import optics, psf
from pipeline.core.colour import srgb_to_linear
from pipeline.core.quality import psnr
from pipeline.io.profiles import load_lens
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.jobs.sweep import profile_from_range

LENS = "fujinon-12.5mm-f1.4-sony-1-3in"
NEAR, FAR, EXPOSURE = 600.0, 3000.0, 0.2


def sweep_args(inputs, output, *extra):
    """``flexdof sweep`` arguments for the Sec. 4.1-like sweep used throughout."""
    paths = [str(p) for p in inputs]
    return [
        "sweep",
        *paths,
        "-o",
        str(output),
        "--lens",
        LENS,
        "--near",
        str(NEAR),
        "--far",
        str(FAR),
        "--exposure",
        str(EXPOSURE),
        *extra,
    ]


@pytest.fixture(scope="module")
def scene():
    sharp = srgb_to_linear(data.astronaut()[100:356, 150:406].astype(np.float32) / 255)
    return sharp


def sweep_capture(sharp, depth_mm):
    """Render a flat scene's sweep capture with the numeric Eq. 5 kernel (independent path)."""
    lens = load_lens(LENS)
    profile = profile_from_range(lens, NEAR, FAR, EXPOSURE)
    kernel = psf.integrated_psf(lens, depth_mm, profile, method="numeric")
    h = kernel.shape[0] // 2
    padded = np.pad(sharp, ((h, h), (h, h), (0, 0)), mode="reflect")
    return np.stack(
        [fftconvolve(padded[..., c], kernel, mode="valid") for c in range(3)], axis=-1
    ).astype(np.float32)


def test_sweep_image_is_sharpened(tmp_path, scene):
    captured = sweep_capture(scene, 1000.0)
    write_image(tmp_path / "capture.tif", captured, encoding="float32")
    out = tmp_path / "edof.tif"
    args = sweep_args([str(tmp_path / "capture.tif")], str(out), "--linear")
    assert main(args) == 0
    restored = read_frame(out)
    assert psnr(restored, scene) > psnr(captured, scene) + 3.0
    assert (tmp_path / "edof.tif.json").is_file()


def test_sequence_and_depth_independence(tmp_path, scene):
    """Frames at different depths all sharpen with the one depth-averaged kernel."""
    paths = []
    for depth in (700.0, 1500.0, 2800.0):
        path = tmp_path / f"frame_{depth:.0f}.tif"
        write_image(path, sweep_capture(scene, depth), encoding="float32")
        paths.append(path)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    args = sweep_args(map(str, paths), str(out_dir), "--linear")
    assert main(args) == 0
    for path in paths:
        restored = read_frame(out_dir / f"{path.stem}_edof.tif")
        assert psnr(restored, scene) > psnr(read_frame(path), scene) + 2.0


def test_edof_video(tmp_path, scene):
    """Sec. 4.2: alternating sweeps share one IPSF; every frame is deconvolved."""
    captured = sweep_capture(scene, 1200.0)
    encoded = (np.clip(captured, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)[..., ::-1]
    video = tmp_path / "sweeps.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5, encoded.shape[1::-1])
    for _ in range(5):
        writer.write(np.ascontiguousarray(encoded))
    writer.release()
    out = tmp_path / "edof.avi"
    args = sweep_args([str(video)], str(out))
    assert main(args) == 0
    reader = cv2.VideoCapture(str(out))
    assert int(reader.get(cv2.CAP_PROP_FRAME_COUNT)) == 5
    ok, frame = reader.read()
    assert ok and frame.shape[:2] == encoded.shape[:2]
    reader.release()
    assert not list(tmp_path.glob(".*partial*"))


def test_sweep_stack_directory(tmp_path, scene):
    lens = load_lens(LENS)
    write_image(tmp_path / "capture.tif", sweep_capture(scene, 900.0), encoding="float32")
    start = optics.image_distance(lens.focal_length_mm, FAR)
    end = optics.image_distance(lens.focal_length_mm, NEAR)
    (tmp_path / "stack.toml").write_text(
        f'lens = "{LENS}"\nkind = "sweep"\n\n[sweep]\nfile = "capture.tif"\n'
        f"start_image_distance_mm = {start}\nend_image_distance_mm = {end}\n"
        f'exposure_s = {EXPOSURE}\nprofile = "constant-speed"\n'
    )
    out = tmp_path / "edof.tif"
    assert main(["stack", str(tmp_path), "-o", str(out), "--float"]) == 0
    assert psnr(read_frame(out), scene) > psnr(read_frame(tmp_path / "capture.tif"), scene) + 3
    # the capture in other units (x 4095), its white level in stack.toml: the same result
    write_image(tmp_path / "capture.tif", read_frame(tmp_path / "capture.tif") * 4095.0,
                encoding="float32")
    toml = tmp_path / "stack.toml"
    toml.write_text("white = 4095\n" + toml.read_text())
    assert main(["stack", str(tmp_path), "-o", str(tmp_path / "counts.tif"), "--float"]) == 0
    np.testing.assert_allclose(read_frame(tmp_path / "counts.tif"), read_frame(out), atol=1e-5)
    assert json.loads((tmp_path / "counts.tif.json").read_text())["white"] == 4095.0


def test_near_beyond_far_is_a_clear_error(tmp_path, capsys):
    (tmp_path / "x.tif").write_bytes(b"")
    code = main(
        [
            "sweep",
            str(tmp_path / "x.tif"),
            "-o",
            str(tmp_path / "o.tif"),
            "--lens",
            LENS,
            "--near",
            "2000",
            "--far",
            "1000",
        ]
    )
    assert code == 2
    assert "--near" in capsys.readouterr().err
    assert not (tmp_path / "o.tif").exists()
