"""The main job (Sec. 9) end to end on synthetic stacks rendered independently of the engine."""

import logging
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import tifffile
from scipy.signal import fftconvolve
from skimage import data

from pipeline.cli import main
from pipeline.core import optics, psf
from pipeline.core.colour import srgb_to_linear
from pipeline.core.quality import psnr
from pipeline.io.profiles import load_lens
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.scheduler import scheduler_context

LENS = "fujinon-12.5mm-f1.4-sony-1-3in"


def blur(image, kernel):
    h = kernel.shape[0] // 2
    padded = np.pad(image, ((h, h), (h, h), (0, 0)), mode="reflect")
    return np.stack(
        [fftconvolve(padded[..., c], kernel, mode="valid") for c in range(image.shape[2])], -1
    )


def make_stack(folder, sharp, depths_mm, positions_mm, *, noise=0.0, seed=0, lens=LENS):
    """Frames of a scene whose columns are split into planes at ``depths_mm`` (Eqs. 2-3)."""
    profile = load_lens(lens)
    rng = np.random.default_rng(seed)
    bands = np.array_split(np.arange(sharp.shape[1]), len(depths_mm))
    lines = [f'lens = "{lens}"', 'kind = "focal-stack"', ""]
    for i, p in enumerate(positions_mm):
        frame = np.zeros_like(sharp)
        for depth, cols in zip(depths_mm, bands):
            mask = np.zeros((*sharp.shape[:2], 1), np.float32)
            mask[:, cols] = 1
            frame += blur(sharp * mask, psf.lens_psf(profile, depth, p))
        frame = frame + rng.normal(0, noise, frame.shape) if noise else frame
        name = f"frame_{i:02d}.tif"
        write_image(folder / name, np.clip(frame, 0, None).astype(np.float32), encoding="float32")
        lines += ["[[frames]]", f'file = "{name}"', f"image_distance_mm = {p}", ""]
    (folder / "stack.toml").write_text("\n".join(lines))
    return folder


@pytest.fixture(scope="module")
def sharp():
    return srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)


def positions_for(near_mm, far_mm, n):
    lo, hi = optics.image_distance(12.5, far_mm), optics.image_distance(12.5, near_mm)
    return np.linspace(lo, hi, n)


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_result_beats_every_frame(tmp_path, sharp, noise):
    stack = make_stack(
        tmp_path, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9), noise=noise
    )
    best_frame = max(psnr(read_frame(f), sharp) for f in sorted(stack.glob("frame_*.tif")))
    scores = {}
    for method in ("wiener", "rl"):  # the command line offers these two
        out = tmp_path / f"{method}.tif"
        code = main(
            ["-q", "stack", str(stack), "-o", str(out), "--float", "--method", method,
             "--align", "none"]
        )
        assert code == 0
        scores[method] = psnr(read_frame(out), sharp)
    out = tmp_path / "sparse.tif"  # the sparse prior: through the API only
    process_stack(stack, out, StackOptions(method="sparse", align="none", encoding="float32"))
    scores["sparse"] = psnr(read_frame(out), sharp)
    for method, score in scores.items():
        assert score > best_frame + 1.0, (method, scores, best_frame)
    if noise:
        assert scores["sparse"] > scores["wiener"]


COARSE_LENS = """focal_length_mm = 12.5
f_number = 1.4
[sensor]
pixel_pitch_um = 25.0
width_px = 256
height_px = 256
"""


def test_analytic_alignment_undoes_breathing(tmp_path, sharp):
    """Frames magnified by p_i / p_ref (Fig. 1) are registered by --align analytic.

    A macro-like sweep (150-2500 mm) breathes by +-4%; 25 um pixels keep the blur small.
    """
    lens = tmp_path / "coarse.toml"
    lens.write_text(COARSE_LENS)
    positions = positions_for(150, 2500, 7)
    stack = make_stack(tmp_path, sharp, [400.0], positions, lens=str(lens))
    import cv2

    ref = positions[len(positions) // 2]
    for i, p in enumerate(positions):
        path = tmp_path / f"frame_{i:02d}.tif"
        frame = read_frame(path)
        s = p / ref
        centre = ((frame.shape[1] - 1) / 2, (frame.shape[0] - 1) / 2)
        m = np.array([[s, 0, centre[0] * (1 - s)], [0, s, centre[1] * (1 - s)]])
        warped = cv2.warpAffine(
            frame, m, frame.shape[1::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        write_image(path, warped, encoding="float32")
    out_none, out_analytic = tmp_path / "none.tif", tmp_path / "analytic.tif"
    assert main(["-q", "stack", str(stack), "-o", str(out_none), "--float", "--align", "none"]) == 0
    assert (
        main(["-q", "stack", str(stack), "-o", str(out_analytic), "--float", "--align", "analytic"])
        == 0
    )
    # Breathing moves pixels by up to ~1.4 px at the edge: compare on the outer ring.
    yy, xx = np.mgrid[:256, :256]
    radius = np.hypot(yy - 127.5, xx - 127.5)
    ring = (radius > 80) & (radius < 115)
    err_none = np.mean(np.abs(read_frame(out_none) - sharp)[ring])
    err_analytic = np.mean(np.abs(read_frame(out_analytic) - sharp)[ring])
    assert err_analytic < 0.8 * err_none, (err_analytic, err_none)


def test_sidecar_records_weights_and_kernel(tmp_path, sharp):
    positions = positions_for(450, 2500, 6)
    stack = make_stack(tmp_path, sharp, [900.0], positions)
    out = tmp_path / "out.png"
    with scheduler_context(threads=2):
        result = process_stack([stack], out, StackOptions(align="none"))
    side = result.sidecar
    weights = [f["weight"] for f in side["frames"]]
    assert sum(weights) == pytest.approx(1.0)
    assert weights == pytest.approx([1 / 6] * 6)  # Sec. 9, even spacing, full end cells
    assert [f["image_distance_mm"] for f in side["frames"]] == pytest.approx(list(positions))
    assert side["kernel"]["source"] in ("stack-average", "analytic-eq6")
    assert set(side["timings_s"]) >= {"read", "align", "accumulate", "deconvolve", "total"}
    assert (tmp_path / "out.png.json").is_file()


def peak_memory(folder, n_frames, shape=(384, 384, 3)):
    rng = np.random.default_rng(1)
    base = rng.random(shape, dtype=np.float32)
    for i in range(n_frames):
        write_image(
            folder / f"f_{i:03d}.tif", base * (0.5 + 0.5 * i / n_frames), encoding="float32"
        )
    tracemalloc.start()
    with scheduler_context(threads=2):
        process_stack(
            [str(folder / "f_*.tif")],
            folder / "out.tif",
            StackOptions(align="none", blur_span_px=12.0, encoding="float32"),
        )
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak


def test_peak_memory_is_flat_in_the_number_of_frames(tmp_path):
    # the least of three runs each: one run's peak moves by up to 3 frames with the threads'
    # timing (8 frames: 12.2-15.7 frames' worth; since stop 35's colour statistics, 21.8-22.8
    # and 32 frames 22.1-24.9), the least of three by far less
    peaks = {}
    for n in (8, 32):
        runs = []
        for k in range(3):
            (tmp_path / f"{n}_{k}").mkdir()
            runs.append(peak_memory(tmp_path / f"{n}_{k}", n))
        peaks[n] = min(runs)
    frame_bytes = 384 * 384 * 3 * 4
    assert peaks[32] < peaks[8] + 3 * frame_bytes, {n: p / frame_bytes for n, p in peaks.items()}


# ----------------------------------------------------------------------------- bad input
def run_cli(args, capsys):
    code = main(args)
    err = capsys.readouterr().err.strip()
    return code, err


def assert_clean_failure(code, err, out, *needles):
    assert code == 2
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err
    assert not out.exists()
    assert not out.with_name(out.name + ".json").exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]


@pytest.fixture
def good_stack(tmp_path, sharp):
    folder = tmp_path / "stack"
    folder.mkdir()
    return make_stack(folder, sharp[:96, :96], [800.0], positions_for(450, 2500, 3))


def test_empty_directory(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    out = tmp_path / "out.tif"
    code, err = run_cli(["stack", str(tmp_path / "empty"), "-o", str(out)], capsys)
    assert_clean_failure(code, err, out, "no image files")


@pytest.mark.parametrize(
    "source", ["focusstack-pcb/pcb7/pcb_001.jpg", "raw-dng-canon550d/colorchart.dng"]
)
def test_truncated_files(tmp_path, capsys, shared_data, source):
    data_bytes = (shared_data / source).read_bytes()
    folder = tmp_path / "s"
    folder.mkdir()
    suffix = source.rsplit(".", 1)[1]
    (folder / f"a.{suffix}").write_bytes(data_bytes)
    (folder / f"b.{suffix}").write_bytes(data_bytes[: len(data_bytes) // 2])
    out = tmp_path / "out.tif"
    code, err = run_cli(["stack", str(folder), "-o", str(out), "--blur-span-px", "5"], capsys)
    assert_clean_failure(code, err, out, f"b.{suffix}")


def test_frames_of_different_sizes(tmp_path, capsys):
    folder = tmp_path / "s"
    folder.mkdir()
    write_image(folder / "a.tif", np.zeros((32, 32), np.float32), encoding="float32")
    write_image(folder / "b.tif", np.zeros((32, 40), np.float32), encoding="float32")
    out = tmp_path / "out.tif"
    code, err = run_cli(["stack", str(folder), "-o", str(out)], capsys)
    assert_clean_failure(code, err, out, "b.tif")


def _missing_file(text):
    return text.replace('file = "frame_01.tif"', 'file = "missing.tif"')


def _two_position_kinds(text):
    return text.replace(
        "image_distance_mm = ", "focus_distance_mm = 900.0\nimage_distance_mm = ", 1
    )


def _focus_inside_f(text):
    first = text.split("image_distance_mm = ")[1].split("\n")[0]
    return text.replace(f"image_distance_mm = {first}", "focus_distance_mm = 10.0", 1)


def _unknown_lens(text):
    return text.replace(LENS, "no-such-lens")


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (_missing_file, "missing.tif"),
        (_two_position_kinds, "frame"),
        (_focus_inside_f, "focal length"),
        (_unknown_lens, "no-such-lens"),
    ],
    ids=["missing-file", "two-position-kinds", "focus-inside-f", "unknown-lens"],
)
def test_bad_sidecars(good_stack, tmp_path, capsys, edit, needle):
    sidecar = good_stack / "stack.toml"
    sidecar.write_text(edit(sidecar.read_text()))
    out = tmp_path / "out.tif"
    code, err = run_cli(["stack", str(good_stack), "-o", str(out)], capsys)
    assert_clean_failure(code, err, out, needle)


def test_existing_output_survives_a_failed_run(good_stack, tmp_path, capsys):
    out = tmp_path / "out.tif"
    assert main(["-q", "stack", str(good_stack), "-o", str(out), "--align", "none"]) == 0
    before = out.read_bytes()
    (good_stack / "frame_01.tif").write_bytes(b"not a tiff")
    code, err = run_cli(["stack", str(good_stack), "-o", str(out), "--align", "none"], capsys)
    assert code == 2 and "frame_01.tif" in err
    assert out.read_bytes() == before


def test_shipped_sample_each_method_beats_the_best_frame(repo_root, tmp_path):
    """stacks/motorcycle (noisy, rendered with occlusion and breathing): PSNR vs ground truth."""
    sample = repo_root / "stacks" / "motorcycle"
    truth = read_frame(sample / "ground_truth.tif")
    best_frame = max(psnr(read_frame(f), truth) for f in sorted(sample.glob("frame_*.png")))
    scores = {}
    with scheduler_context(threads=2):
        for method in ("wiener", "rl", "sparse"):
            job = process_stack(
                [sample],
                tmp_path / f"{method}.tif",
                StackOptions(method=method, encoding="float32"),
            )
            scores[method] = psnr(job.image, truth)
    assert min(scores.values()) > best_frame + 4.0, (scores, best_frame)
    assert scores["sparse"] > scores["wiener"], scores


def test_nan_or_inf_pixels_name_the_frame(tmp_path, capsys):
    folder = tmp_path / "s"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        frame = rng.random((48, 48), dtype=np.float32)
        if i == 1:
            frame[5, 5], frame[9, 9] = np.nan, np.inf
        tifffile.imwrite(folder / f"f{i}.tif", frame)
    out = tmp_path / "out.tif"
    code, err = run_cli(["stack", str(folder), "-o", str(out), "--blur-span-px", "5"], capsys)
    assert_clean_failure(code, err, out, "f1.tif", "2 pixel values")


def test_progress_reports_every_frame(repo_root, tmp_path):
    seen = []
    with scheduler_context(threads=2):
        process_stack(
            [repo_root / "stacks" / "motorcycle"],
            tmp_path / "o.tif",
            StackOptions(),
            progress=lambda stage, done, total: seen.append((stage, done, total)),
        )
    for stage in ("preview", "accumulate"):
        counts = [done for s, done, total in seen if s == stage]
        assert set(counts) >= set(range(1, 9)) and max(counts) == 8
    assert [s for s, _, _ in seen][-1] == "deconvolve"


def test_a_single_frame_is_a_clear_error(tmp_path, capsys):
    write_image(tmp_path / "only.tif", np.full((32, 32), 0.5, np.float32), encoding="float32")
    out = tmp_path / "out.tif"
    code, err = run_cli(["stack", str(tmp_path / "only.tif"), "-o", str(out)], capsys)
    assert_clean_failure(code, err, out, "only.tif", "at least two frames")


def test_lens_option_path_is_relative_to_the_working_directory(good_stack, tmp_path, monkeypatch):
    (tmp_path / "work").mkdir()
    lens_text = Path(load_lens(LENS).source).read_text()
    (tmp_path / "work" / "mine.toml").write_text(lens_text)
    monkeypatch.chdir(tmp_path / "work")
    assert main(["-q", "stack", str(good_stack), "-o", "out.tif", "--lens", "mine.toml"]) == 0
    assert (tmp_path / "work" / "out.tif").is_file()


def test_float_frames_in_other_units_take_their_white_level(tmp_path, sharp, caplog, capsys):
    """Clipping and the frames' range assume white at 1: float frames far above it are not
    refused (they are linear light) but the user is told to give their white level. With
    it (``--white`` or ``white`` in stack.toml) the job is the one of the frames in [0, 1]:
    the three planes scaled by 1000 came out at 29.61 against 30.60 dB without it."""
    folder = tmp_path / "stack"
    folder.mkdir()
    planes = [500.0, 800.0, 1600.0]
    make_stack(folder, sharp[:96, :96], planes, positions_for(450, 2500, 5), noise=0.01)

    def run(name, **options):
        return process_stack(
            folder, tmp_path / name, StackOptions(encoding="float32", blur_span_px=6.0, **options)
        )

    def warnings():
        return [r.getMessage() for r in caplog.records if "white is 1" in r.getMessage()]

    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        unit = run("unit.tif")
    unit_multi = run("unit_multi.tif", method="multiframe")  # it reads the frames again
    assert not warnings() and unit.sidecar["white"] is None
    for path in sorted(folder.glob("frame_*.tif")):
        write_image(path, read_frame(path) * 1000.0, encoding="float32")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        scaled = run("scaled.tif")
    (message,) = warnings()
    assert "--white LEVEL" in message and "white = LEVEL in stack.toml" in message
    assert scaled.sidecar["frame_range"]["flat_fraction"] == 0  # the range did nothing
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        given = run("given.tif", white=1000.0)
    assert not warnings() and given.sidecar["white"] == 1000.0
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        run("low.tif", white=100.0)  # a white level given, but 10x too low
    messages = [r.getMessage() for r in caplog.records]
    (message,) = [m for m in messages if "white level 100 given" in m]
    assert "check --white" in message
    assert unit.sidecar["frame_range"]["flat_fraction"] > 0
    assert given.sidecar["frame_range"] == unit.sidecar["frame_range"]
    # x * 1000 / 1000 is x to float32's rounding; where that rounding crosses a 16-bit code's
    # edge, a pixel moves into or out of the colour clip (since stop 35's colour differences:
    # at most 8.7e-7 in some runs, 1.05e-5 at 2 of 27648 values in others; 1.2e-6 before)
    np.testing.assert_allclose(given.image, unit.image, atol=5e-5)
    given_multi = run("given_multi.tif", white=1000.0, method="multiframe")
    np.testing.assert_allclose(given_multi.image, unit_multi.image, atol=5e-5)
    assert np.max(np.abs(scaled.image / 1000.0 - unit.image)) > 0.01  # not so without it
    toml = folder / "stack.toml"
    toml.write_text("white = 1000\n" + toml.read_text())
    from_toml = run("toml.tif")
    assert from_toml.sidecar["white"] == 1000.0
    np.testing.assert_array_equal(from_toml.image, given.image)
    out = tmp_path / "cli.tif"
    code, err = run_cli(["stack", str(folder), "-o", str(out), "--white", "-5"], capsys)
    assert_clean_failure(code, err, out, "white", "> 0")
