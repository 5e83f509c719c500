"""Issue 16: ingestion safety, atomic results, limits derived from the image.

Each test fails on the code before the fix (the issue's reproductions, made small).
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import sys
import textwrap
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.io.read import read_frame, read_preview
from pipeline.io.stackfile import load_stack
from pipeline.jobs.options import StackOptions, megapixels
from pipeline.jobs.stack import process_stack

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "stacks" / "motorcycle"
FRAMES = [f"frame_{i:02d}.png" for i in range(8)]


@pytest.fixture
def sample(tmp_path) -> Path:
    """A copy of the shipped sample (stack.toml, lens.toml, 8 frames)."""
    folder = tmp_path / "motorcycle"
    folder.mkdir()
    for name in [*FRAMES, "stack.toml", "lens.toml"]:
        shutil.copy(SAMPLE / name, folder / name)
    return folder


@pytest.fixture
def frames_only(tmp_path) -> Path:
    """The sample's frames without stack.toml: every image in the folder is a frame."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in FRAMES:
        shutil.copy(SAMPLE / name, folder / name)
    return folder


def _no_work(monkeypatch):
    """Make the expensive phase fail the test: checks must come before it."""

    def forbidden(*args, **kwargs):
        raise AssertionError("the job started working before refusing its output")

    monkeypatch.setattr("pipeline.jobs.stack.accumulate", forbidden)
    monkeypatch.setattr("pipeline.jobs.stack.align_stack", forbidden)


def _temps(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


# ----------------------------------------------------------------------------- ingestion
def test_second_run_does_not_take_its_own_result_as_a_frame(frames_only, caplog):
    # flexdof stack DIR -o DIR/sharp.png, twice: the second run must not read sharp.png.
    out = frames_only / "sharp.png"
    options = StackOptions(blur_span_px=12.0)
    first = process_stack(frames_only, out, options)
    with caplog.at_level(logging.WARNING):
        second = process_stack(frames_only, out, options)
    assert len(second.sidecar["inputs"]) == len(first.sidecar["inputs"]) == 8
    assert second.sidecar["kernel"] == {**first.sidecar["kernel"]}
    assert "sharp.png: it is a flexdof result" in caplog.text
    assert [f.name for f in load_stack(str(frames_only / "*.png")).files] == FRAMES


def test_pcb7_folder_skips_another_tools_result_with_a_warning(shared_data, caplog):
    folder = shared_data / "focusstack-pcb" / "pcb7"
    with caplog.at_level(logging.WARNING):
        stack = load_stack(folder)
    assert "expected.jpg" not in [f.name for f in stack.files]
    assert len(stack) == 7
    assert "skipping expected.jpg: its name looks like a finished result" in caplog.text
    # Named explicitly, it is taken (the user asked for it).
    assert load_stack([folder / "expected.jpg", folder / "pcb_001.jpg"]).files[0].name == (
        "expected.jpg"
    )


@pytest.mark.parametrize("name", ["result.png", "output.tif", "pcb_edof.jpg", "stacked.tif"])
def test_other_result_names_are_skipped(frames_only, name):
    shutil.copy(frames_only / FRAMES[0], frames_only / (Path(name).stem + ".png"))
    assert [f.name for f in load_stack(frames_only).files] == FRAMES


def test_hidden_files_are_not_frames(frames_only):
    """A Mac leaves ``._NAME`` resource forks beside every file on a card (FAT, exFAT)."""
    for name in FRAMES:
        (frames_only / f"._{name}").write_bytes(b"\x00\x05\x16\x07\x00\x02\x00\x00Mac OS X")
    (frames_only / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")
    assert [f.name for f in load_stack(frames_only).files] == FRAMES


def test_raw_plus_jpeg_shots_stack_the_raw_files(tmp_path, shared_data, caplog):
    """A camera set to RAW+JPEG writes each shot twice; the RAW files are the frames."""
    dng = shared_data / "raw-dng-canon550d" / "colorchart.dng"
    for i in (1, 2, 10):
        shutil.copy(dng, tmp_path / f"IMG_{i:04d}.DNG")
        cv2.imwrite(str(tmp_path / f"IMG_{i:04d}.JPG"), np.zeros((8, 8, 3), np.uint8))
    with caplog.at_level(logging.WARNING):
        stack = load_stack(tmp_path)
    assert [f.name for f in stack.files] == ["IMG_0001.DNG", "IMG_0002.DNG", "IMG_0010.DNG"]
    assert "each shot is there as RAW and as .JPG (IMG_0001.DNG, IMG_0001.JPG)" in caplog.text
    assert "stacking the 3 RAW files" in caplog.text and "*.JPG" in caplog.text
    # Named by a glob, the JPEGs are taken.
    assert [f.suffix for f in load_stack(str(tmp_path / "*.JPG")).files] == [".JPG"] * 3


@pytest.mark.parametrize("extra", ["png", "raw_short"])
def test_shots_twice_in_other_formats_are_refused_by_name(frames_only, shared_data, extra):
    if extra == "png":  # the same frames exported twice: which to take is the user's call
        for name in FRAMES:
            cv2.imwrite(str(frames_only / name.replace(".png", ".tif")), np.zeros((8, 8), np.uint8))
    else:  # a RAW twin for one shot only: the others would mix RAW and PNG frames
        dng = shared_data / "raw-dng-canon550d" / "colorchart.dng"
        shutil.copy(dng, frames_only / "frame_03.dng")
    with pytest.raises(InputError, match=r"frame_0\d is there 2 times \(frame_0\d\.\w+, frame_0"):
        load_stack(frames_only)


def test_output_that_is_an_input_frame_is_refused(sample, monkeypatch):
    frame = sample / "frame_03.png"
    before = frame.read_bytes()
    monkeypatch.setattr(
        "pipeline.jobs.stack.accumulate",
        lambda *a, **k: (_ for _ in ()).throw(AssertionError("work started")),
    )
    with pytest.raises(InputError, match=r"frame_03.png is one of the input frames"):
        process_stack(sample, frame)
    assert frame.read_bytes() == before


def test_lens_profile_for_another_resolution_warns(sample, caplog):
    lens = sample / "lens.toml"
    text = lens.read_text().replace("width_px = 370", "width_px = 1024")
    lens.write_text(text.replace("height_px = 250", "height_px = 768"))
    with caplog.at_level(logging.WARNING):
        process_stack(sample, sample / "out.tif")
    assert "the frames are 370x250 px but lens profile" in caplog.text
    assert "1024x768 px sensor" in caplog.text


def test_matching_lens_profile_does_not_warn(sample, caplog):
    with caplog.at_level(logging.WARNING):
        process_stack(sample, sample / "out.tif")
    assert "lens profile" not in caplog.text


# ----------------------------------------------------------------------------- atomic results
def test_sidecar_failure_leaves_the_previous_pair_intact(sample, monkeypatch):
    out = sample / "out.tif"
    process_stack(sample, out)
    image, sidecar = out.read_bytes(), (sample / "out.tif.json").read_bytes()
    from pipeline.jobs import stack as stack_job

    real = stack_job.stack_sidecar

    def broken(*args, **kwargs):  # a sidecar that cannot be encoded (NaN has no JSON form)
        return {**real(*args, **kwargs), "broken": float("nan")}

    monkeypatch.setattr(stack_job, "stack_sidecar", broken)
    with pytest.raises(InputError, match="JSON"):
        process_stack(sample, out, StackOptions(method="rl"))
    assert out.read_bytes() == image  # not the new image beside the old sidecar
    assert (sample / "out.tif.json").read_bytes() == sidecar
    assert _temps(sample) == []


def test_save_kernel_into_a_missing_folder_fails_before_the_image_is_replaced(
    sample, monkeypatch
):
    out = sample / "out.tif"
    process_stack(sample, out)
    image = out.read_bytes()
    _no_work(monkeypatch)
    with pytest.raises(InputError, match=r"--save-kernel .*the folder .*missing does not exist"):
        process_stack(sample, out, StackOptions(save_kernel=sample / "missing" / "k.tif"))
    assert out.read_bytes() == image


def test_output_problems_are_found_before_the_work(sample, monkeypatch):
    _no_work(monkeypatch)
    (sample / "dir.tif").mkdir()
    with pytest.raises(InputError, match="is a folder"):
        process_stack(sample, sample / "dir.tif")
    with pytest.raises(InputError, match=r"the file name is 30\d bytes long"):
        process_stack(sample, sample / ("x" * 300 + ".tif"))
    (sample / "ro").mkdir()
    if os.geteuid() == 0:  # root writes anywhere: make the folder refuse new files instead
        import tempfile

        def refuse(*args, **kwargs):
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(tempfile, "mkstemp", refuse)
    else:
        (sample / "ro").chmod(0o555)
    with pytest.raises(InputError, match=r"ro/out.tif: cannot write here \(Permission denied"):
        process_stack(sample, sample / "ro" / "out.tif")


_SIGTERM_JOB = textwrap.dedent(
    """
    import sys, time
    from pipeline.io.write import install_signal_cleanup
    from pipeline.jobs import result
    from pipeline.jobs.stack import process_stack

    install_signal_cleanup()
    real = result.encode_json

    def slow(path, obj):  # the image is staged; the sidecar is being written
        print("writing", flush=True)
        time.sleep(60)
        return real(path, obj)

    result.encode_json = slow
    try:
        process_stack(sys.argv[1], sys.argv[2])
    except KeyboardInterrupt:
        sys.exit(130)
    """
)


@pytest.mark.timeout(120)
def test_sigterm_while_writing_removes_the_temporaries(sample):
    out = sample / "out.tif"
    proc = subprocess.Popen(
        [sys.executable, "-c", _SIGTERM_JOB, str(sample), str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "writing"
        assert [n for n in _temps(sample) if n.startswith(".out.tif.")]  # mid-write
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 130  # handled like Ctrl-C
    finally:
        proc.kill()
        proc.stdout.close()
    assert _temps(sample) == []
    assert not out.exists()


def test_a_later_write_removes_temporaries_of_a_killed_run(tmp_path):
    from pipeline.io import write

    script = textwrap.dedent(
        f"""
        import os, signal
        from pipeline.io.write import stage_bytes
        stage_bytes({str(tmp_path / "out.png")!r}, b"x" * 1000)
        os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    subprocess.run([sys.executable, "-c", script], check=False, timeout=60)
    left = _temps(tmp_path)
    assert len(left) == 1 and left[0].startswith(".out.png.flexdof-")
    alive = tmp_path / f".out.png.flexdof-{write._HOST}-1.abcd.tmp"  # pid 1 runs: not ours
    alive.write_bytes(b"")
    other = tmp_path / ".out.png.something.tmp"  # not provably flexdof's
    other.write_bytes(b"")
    write.write_image(tmp_path / "out.png", np.zeros((4, 4), np.float32))
    assert _temps(tmp_path) == sorted([alive.name, other.name])


# ----------------------------------------------------------------------------- limits
def _tiny_stack(folder: Path, rows: int, cols: int, n: int = 4) -> Path:
    folder.mkdir()
    rng = np.random.default_rng(0)
    base = rng.random((rows, cols, 3))
    for i in range(n):
        img = cv2.GaussianBlur(base, (3, 3), 0.5 + 0.5 * i)
        cv2.imwrite(str(folder / f"f{i}.png"), (img * 255).astype(np.uint8))
    return folder


@pytest.mark.timeout(60)
def test_3x3_frames_are_refused_at_once(tmp_path):
    folder = _tiny_stack(tmp_path / "tiny", 3, 3)
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"the frames are 3x3 px; flexdof needs at least 8x8"):
        process_stack(folder, tmp_path / "out.tif")
    assert time.monotonic() - t0 < 10


@pytest.mark.timeout(60)
def test_16x11_frames_finish_fast(tmp_path):
    folder = _tiny_stack(tmp_path / "tiny", 11, 16)
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"cannot measure the blur .*--blur-span-px"):
        process_stack(folder, tmp_path / "out.tif")
    result = process_stack(folder, tmp_path / "out.tif", StackOptions(blur_span_px=3.0))
    assert result.image.shape == (11, 16, 3)
    assert time.monotonic() - t0 < 20  # was 110 s and 10 GB


def _huge_png(path: Path, side: int) -> None:
    """A valid grey PNG of side x side black pixels: ~250 KB on disk."""
    row = b"\x00" + bytes(side)
    comp = zlib.compressobj(9)
    body = b"".join(comp.compress(row) for _ in range(side)) + comp.flush()

    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) & 0xFFFFFFFF
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", body) + chunk(b"IEND", b"")
    )


@pytest.mark.timeout(60)
def test_pixel_limit_refuses_a_decompression_bomb_before_decoding(tmp_path):
    folder = tmp_path / "bomb"
    folder.mkdir()
    for i in range(2):
        _huge_png(folder / f"f{i}.png", 16000)
    assert (folder / "f0.png").stat().st_size < 400_000
    with pytest.raises(InputError, match=r"16000x16000 px \(256 Mpx\).*--max-pixels"):
        process_stack(folder, tmp_path / "out.tif")
    with pytest.raises(InputError, match="max_pixels"):
        StackOptions(max_pixels=0)


@pytest.mark.timeout(60)
def test_pixel_limit_below_a_megapixel_is_printed_as_it_is(sample, tmp_path):
    # 0.0925 Mpx frames against a 0.05 Mpx limit: both read "0 Mpx" before
    options = StackOptions(max_pixels=50_000)
    with pytest.raises(InputError, match=r"370x250 px \(0\.0925 Mpx\).*limit of 0\.05 Mpx"):
        process_stack(sample, tmp_path / "out.tif", options)


@pytest.mark.parametrize(
    "pixels, shown",
    [(92_500, "0.0925"), (375_000, "0.375"), (12_582_912, "12.6"), (99_400_000, "99.4"),
     (256_000_000, "256"), (65535 * 65535, "4295")],
)
def test_megapixels_print_without_exponents(pixels, shown):
    assert megapixels(pixels) == shown


@pytest.mark.timeout(60)
def test_blur_span_larger_than_the_frame_is_refused(sample):
    with pytest.raises(InputError, match=r"--blur-span-px gives a blur span of 4000 px.*447 px"):
        process_stack(sample, sample / "out.tif", StackOptions(blur_span_px=4000.0))


@pytest.mark.timeout(60)
def test_tile_px_1_is_not_slow(sample):
    t0 = time.monotonic()
    process_stack(sample, sample / "out.tif", StackOptions(tile_px=1, method="rl"))
    assert time.monotonic() - t0 < 30


def test_absurd_image_distance_names_stack_toml_and_the_frame(sample):
    toml = sample / "stack.toml"
    text = toml.read_text().replace("image_distance_mm = 12.578616", "image_distance_mm = 1e300")
    toml.write_text(text)
    with pytest.raises(InputError, match=r"stack.toml: image_distance_mm = 1e\+300 of frame_00"):
        load_stack(sample)


def _corrupt_jpeg(path: Path) -> None:
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur((rng.random((256, 256, 3)) * 255).astype(np.uint8), (5, 5), 2)
    data = bytearray(cv2.imencode(".jpg", image)[1].tobytes())
    sos = data.find(b"\xff\xda")
    middle = sos + (len(data) - sos) // 2
    for k in range(200):  # garbage in the scan, never a marker
        i = middle + 7 * k
        if data[i - 1] != 0xFF and data[i] != 0xFF:
            data[i] = int(rng.integers(0, 0xFF))
    path.write_bytes(bytes(data))


def test_corrupt_jpeg_scan_data_is_an_error_naming_the_file(tmp_path):
    bad = tmp_path / "frame_07.jpg"
    _corrupt_jpeg(bad)
    with pytest.raises(InputError, match=r"frame_07.jpg: corrupt JPEG data \(libjpeg: "):
        read_frame(bad)
    with pytest.raises(InputError, match=r"frame_07.jpg: corrupt JPEG data"):
        read_preview(bad, 64)


def test_a_corrupt_jpeg_among_frames_decoding_side_by_side_is_pinned_on_its_file(tmp_path):
    """Decoders share one stderr capture (issue 15: frames decode in parallel); a
    warning seen while several decoded is attributed by decoding each suspect alone."""
    from concurrent.futures import ThreadPoolExecutor

    bad = tmp_path / "frame_07.jpg"
    _corrupt_jpeg(bad)
    rng = np.random.default_rng(4)
    goods = []
    for i in range(6):
        good = tmp_path / f"frame_{i:02d}.jpg"
        cv2.imwrite(str(good), (rng.random((384, 512, 3)) * 255).astype(np.uint8))
        goods.append(good)
    paths = [*goods[:3], bad, *goods[3:]] * 3

    def outcome(path):
        try:
            return read_frame(path).shape
        except InputError as err:
            return str(err)

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(outcome, paths))
    for path, result in zip(paths, results):
        if path == bad:
            assert result.startswith(f"{bad}: corrupt JPEG data (libjpeg: "), result
        else:
            assert result == (384, 512, 3), (path, result)
    assert read_frame(goods[0]).shape == (384, 512, 3)  # the capture window was closed


def test_a_sound_jpeg_still_reads(tmp_path):
    good = tmp_path / "good.jpg"
    cv2.imwrite(str(good), np.full((32, 48, 3), 128, np.uint8))
    assert read_frame(good).shape == (32, 48, 3)


def test_sidecar_records_only_frames(frames_only):
    out = frames_only / "x.png"
    process_stack(frames_only, out, StackOptions(blur_span_px=10.0))
    data = json.loads((frames_only / "x.png.json").read_text())
    assert all(Path(p).name in FRAMES for p in data["inputs"])


def test_float_frames_of_1e38_are_restored_not_non_finite(sample):
    import tifffile

    toml = sample / "stack.toml"
    toml.write_text(toml.read_text().replace(".png", ".tif"))
    for name in FRAMES:
        frame = read_frame(sample / name) * np.float32(1e38)
        tifffile.imwrite(
            sample / name.replace(".png", ".tif"), frame.astype(np.float32), photometric="rgb"
        )
        (sample / name).unlink()
    for method in ("wiener", "rl"):
        result = process_stack(sample, sample / "out.tif", StackOptions(method=method))
        assert np.all(np.isfinite(result.image)) and result.image.max() > 1e37


def test_non_finite_restoration_names_the_frames():
    from pipeline.jobs.result import restore_image

    image = np.ones((32, 32), np.float32)
    image[3, 4] = np.inf
    with pytest.raises(InputError, match=r"^stack/ \(8 frames\): the average .* 1 non-finite"):
        restore_image(image, np.ones((3, 3)) / 9, StackOptions(), source="stack/ (8 frames)")


@pytest.mark.timeout(30)
def test_stack_scheduler_on_a_closed_port_fails_at_once():
    from pipeline.parallel.scheduler import SchedulerError, scheduler_context

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(SchedulerError, match="nothing listens on port"):
        with scheduler_context(f"tcp://127.0.0.1:{port}"):
            pass
    assert time.monotonic() - t0 < 5  # was 10 s


@pytest.mark.timeout(60)
def test_a_sweep_blurring_beyond_the_frame_is_refused_before_its_kernel(sample):
    (sample / "stack.toml").write_text(
        'lens = "lens.toml"\nkind = "sweep"\n[sweep]\nfile = "frame_00.png"\n'
        "start_image_distance_mm = 12.5\nend_image_distance_mm = 1250.0\nexposure_s = 1.0\n"
    )
    t0 = time.monotonic()
    with pytest.raises(InputError, match=r"frame_00.png: the sweep .* more than the image's diag"):
        process_stack(sample, sample / "out.tif")
    assert time.monotonic() - t0 < 10


def test_frames_named_like_results_are_kept_when_they_are_the_frames(tmp_path):
    folder = tmp_path / "extracted"
    folder.mkdir()
    for i in range(3):  # what a video-frame extractor writes
        shutil.copy(SAMPLE / FRAMES[i], folder / f"output_{i + 1:04d}.png")
    assert len(load_stack(folder)) == 3
    for name in ("result.png", "stacked.png"):  # two result-like names, two other frames
        shutil.copy(SAMPLE / FRAMES[0], tmp_path / name)
    for name in FRAMES[:2]:
        shutil.copy(SAMPLE / name, tmp_path / name)
    assert len(load_stack(tmp_path)) == 4  # not a minority: kept


def test_a_frame_overexposed_over_a_large_area_is_warned_about(tmp_path, caplog):
    """One frame of nine clipped at white over its top 40% (an overexposed frame): the
    result stays finite and the job warns, naming the share and what to do; the same stack
    without it does not warn (the real stacks' clipped shares are 0-4%)."""
    from skimage import data
    from test_engine import make_stack, positions_for

    from pipeline.core.colour import srgb_to_linear
    from pipeline.io.write import write_image

    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    make_stack(tmp_path, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9))
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        process_stack(tmp_path, tmp_path / "plain.tif", StackOptions(encoding="float32"))
    assert "clipped (at white)" not in caplog.text
    (tmp_path / "plain.tif").unlink()
    (tmp_path / "plain.tif.json").unlink()
    frame = read_frame(tmp_path / "frame_04.tif")
    frame[: int(0.4 * frame.shape[0])] = 1.0
    write_image(tmp_path / "frame_04.tif", frame, encoding="float32")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        job = process_stack(tmp_path, tmp_path / "over.tif", StackOptions(encoding="float32"))
    assert np.all(np.isfinite(job.image))
    warned = [r.getMessage() for r in caplog.records if "clipped (at white)" in r.getMessage()]
    assert len(warned) == 1 and re.search(r"\b4[0-3]% of the image", warned[0])  # 41% read
    assert "leave the overexposed frames out" in warned[0]


# --- blank frames (a misfire, the lens cap, a black or white frame) --------------------------
BEETLE = ["DSC_0356.jpg", "DSC_0361.jpg", "DSC_0367.jpg"]


@pytest.mark.shared_data
@pytest.mark.parametrize("level", [0, 255])
def test_a_blank_frame_is_left_out_and_the_result_is_the_stack_without_it(
    shared_data, tmp_path, caplog, level
):
    """Three of beetle's frames with a black (or white) JPEG among them, named in focus
    order: the blank frame is left out with a warning naming it, the sidecar lists it, and
    the result is the three frames' own, to float32 rounding (bit for bit under OpenCV 5.0;
    5.1 sums a few pixels in another order: 1.2e-7). Kept, a black frame made the blur-span
    fit read 400 px (the search's end) and the result rang over the whole image."""
    plain, mixed = tmp_path / "plain", tmp_path / "mixed"
    plain.mkdir(), mixed.mkdir()
    for i, name in enumerate(BEETLE):
        for folder in (plain, mixed):
            shutil.copy(shared_data / "chimpstackr-beetle" / name, folder / f"f{2 * i}.jpg")
    shape = cv2.imread(str(plain / "f0.jpg")).shape
    cv2.imwrite(str(mixed / "f1.jpg"), np.full(shape, level, np.uint8))
    expected = process_stack(plain, tmp_path / "plain.tif")
    with caplog.at_level(logging.WARNING, logger="pipeline.jobs.stack"):
        job = process_stack(mixed, tmp_path / "mixed.tif")
    assert job.sidecar["left_out"] == ["f1.jpg"]
    assert [f["file"] for f in job.sidecar["frames"]] == ["f0.jpg", "f2.jpg", "f4.jpg"]
    (warned,) = [r.getMessage() for r in caplog.records if "left out" in r.getMessage()]
    assert "f1.jpg" in warned and "blank" in warned
    assert expected.sidecar["left_out"] == []
    np.testing.assert_allclose(job.image, expected.image, rtol=1e-6, atol=1e-7)


@pytest.mark.shared_data
def test_a_frame_defocused_far_beyond_the_subject_is_not_blank(shared_data):
    """Defocus takes a frame's fine detail far more than its contrast: beetle's frames, one of
    them blurred by a Gaussian of 40 px (far more than any frame of the stack; it keeps 0.43
    of the stack's median spread), are all content;
    a black, a white, a flat grey and a sensor-noise-only frame are blank; a stack whose
    every frame is flat has nothing to compare with and keeps them all."""
    from pipeline.jobs.stack import blank_frames

    previews = [
        read_preview(shared_data / "chimpstackr-beetle" / name, 768) for name in BEETLE
    ]
    defocused = cv2.GaussianBlur(previews[0], (0, 0), 40 * 768 / 750)
    rng = np.random.default_rng(3)
    noise = np.abs(rng.normal(0.0, 2e-4, previews[0].shape)).astype(np.float32)
    blanks = [np.zeros_like(defocused), np.ones_like(defocused), np.full_like(defocused, 0.2)]
    assert blank_frames([*previews, defocused]) == []
    assert blank_frames([*previews, defocused, *blanks, noise]) == [4, 5, 6, 7]
    assert blank_frames(blanks) == []


def test_a_stack_left_with_one_frame_once_blanks_are_out_is_refused(tmp_path, capsys):
    """Two frames, one black: one line names the blank frame and says what to do."""
    from pipeline.cli import main

    shutil.copy(SAMPLE / FRAMES[0], tmp_path / "a.png")
    shape = cv2.imread(str(SAMPLE / FRAMES[0])).shape
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros(shape, np.uint8))
    assert main(["stack", str(tmp_path), "-o", str(tmp_path / "out.tif")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "b.png" in err and "blank" in err and "fewer than two frames" in err
    assert not (tmp_path / "out.tif").exists()


def test_a_blank_frame_leaves_with_its_focus_position(sample, capsys):
    """The shipped sample (stack.toml gives each frame's image distance) with frame 3
    overwritten by a black frame, through the CLI: the other seven keep their own positions
    from stack.toml, and the --json summary names the frame left out."""
    import tomllib

    from pipeline.cli import main

    listed = tomllib.loads((sample / "stack.toml").read_text())["frames"]
    expected = {f["file"]: f["image_distance_mm"] for f in listed if f["file"] != FRAMES[3]}
    shape = cv2.imread(str(sample / FRAMES[3])).shape
    cv2.imwrite(str(sample / FRAMES[3]), np.zeros(shape, np.uint8))
    out = sample.parent / "out.tif"
    assert main(["stack", str(sample), "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["left_out"] == [FRAMES[3]] and summary["frames"] == 7
    sidecar = json.loads(Path(f"{out}.json").read_text())
    assert sidecar["left_out"] == [FRAMES[3]]
    got = {f["file"]: f["image_distance_mm"] for f in sidecar["frames"]}
    assert got == pytest.approx(expected)


def test_flexible_dof_leaves_a_blank_frame_out_too(sample, capsys):
    """flexdof dof shares the stack's alignment: with frame 3 of the sample black it uses the
    other seven (before, the weights of seven frames met a count of eight: an internal error)."""
    from pipeline.cli import main

    shape = cv2.imread(str(sample / FRAMES[3])).shape
    cv2.imwrite(str(sample / FRAMES[3]), np.zeros(shape, np.uint8))
    out = sample.parent / "dof.tif"
    assert main(["dof", str(sample), "-o", str(out), "--in-focus", "450:600", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["left_out"] == [FRAMES[3]] and summary["frames"] == 7
    assert 0 < summary["frames_used"] <= 7
