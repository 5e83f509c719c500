"""Frame weights (Sec. 9 applied to Sec. 5-7) against independent sweep simulations,
and ``flexdof dof`` end to end on a synthetic stack."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline import cli
from pipeline.core import motion, optics
from pipeline.core.weights import constant_speed_weights, discontinuous_weights, row_weights
from pipeline.errors import InputError
from pipeline.io import read, write

positions_st = st.lists(
    st.sampled_from(np.round(np.linspace(12.5, 12.9, 41), 4).tolist()), min_size=1, max_size=12
)


def _nearest_time_shares(p, lo, hi, n=200_001):
    """A constant-speed sweep over [lo, hi], sampled: time nearest each distinct frame."""
    p = np.asarray(p, float)
    samples = np.linspace(lo, hi, n)
    unique = np.unique(p)
    nearest = np.argmin(np.abs(samples[:, None] - unique[None, :]), axis=1)
    share = np.bincount(nearest, minlength=unique.size) / n
    counts = np.array([np.sum(p == u) for u in unique])
    return np.array([share[np.searchsorted(unique, x)] / counts[np.searchsorted(unique, x)]
                     for x in p])


def _interp_time_shares(p, lo, hi, n=20_001):
    """A sweep over [lo, hi], each instant split between the two frames around it (np.interp)."""
    p = np.asarray(p, float)
    unique = np.unique(p)
    samples = np.linspace(lo, hi, n) if hi > lo else np.array([lo])
    share = np.array([np.interp(samples, unique, np.eye(unique.size)[k]).mean()
                      for k in range(unique.size)])
    counts = np.array([np.sum(p == u) for u in unique])
    idx = np.searchsorted(unique, p)
    return share[idx] / counts[idx]


@settings(max_examples=60, deadline=None)
@given(positions_st)
def test_constant_speed_weights_match_a_sampled_sweep(p):
    w = constant_speed_weights(p)
    assert w.sum() == pytest.approx(1.0)
    if len(set(p)) == 1:
        np.testing.assert_allclose(w, 1 / len(p))
    else:
        np.testing.assert_allclose(w, _nearest_time_shares(p, min(p), max(p)), atol=2e-5)


def test_constant_speed_weights_single_frame_and_unsorted_duplicates():
    np.testing.assert_array_equal(constant_speed_weights([12.7]), [1.0])
    p = [12.8, 12.5, 12.6, 12.6, 12.9]
    # by hand, sorted 12.5 | 12.6 x2 | 12.8 | 12.9: cells 0.05, 0.15 (shared), 0.15, 0.05 of 0.4
    np.testing.assert_allclose(constant_speed_weights(p), [0.375, 0.125, 0.1875, 0.1875, 0.125])


@settings(max_examples=60, deadline=None)
@given(positions_st, st.floats(0, 1), st.floats(0, 1))
def test_discontinuous_single_range_is_an_interpolated_sweep(p, a, b):
    lo_p, hi_p = min(p), max(p)
    lo, hi = sorted((lo_p + a * (hi_p - lo_p), lo_p + b * (hi_p - lo_p)))
    w = discontinuous_weights(p, [(hi, lo)], [2.0])
    assert w.sum() == pytest.approx(1.0)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w, _interp_time_shares(p, lo, hi), atol=1e-4)


def test_discontinuous_full_range_equals_constant_speed():
    p = [12.52, 12.9, 12.61, 12.61, 12.7, 12.55]
    np.testing.assert_allclose(
        discontinuous_weights(p, [(12.52, 12.9)], [1]), constant_speed_weights(p), atol=1e-15
    )


def test_discontinuous_concentrates_on_the_ranges():
    rng = np.random.default_rng(1)
    p = rng.permutation(np.linspace(12.5, 12.86, 37))  # 10 um steps, shuffled
    ranges = [(12.535, 12.585), (12.80, 12.80)]
    w = discontinuous_weights(p, ranges, [0.7, 0.3])
    step = 0.01
    inside = ((p >= 12.535 - 1e-9) & (p <= 12.585 + 1e-9)) | np.isclose(p, 12.80)
    near = ((p >= 12.535 - step) & (p <= 12.585 + step)) | np.isclose(p, 12.80)
    assert w[near].sum() == pytest.approx(1.0)
    assert w[inside].sum() > 0.9
    assert w[np.isclose(p, 12.80)].sum() == pytest.approx(0.3)
    np.testing.assert_allclose(w, 0.7 * _interp_time_shares(p, *ranges[0])
                               + 0.3 * _interp_time_shares(p, 12.8, 12.8), atol=1e-4)


def test_discontinuous_errors():
    p = [12.5, 12.6, 12.7]
    with pytest.raises(InputError, match="outside the stack's focus positions"):
        discontinuous_weights(p, [(12.4, 12.6)], [1])
    w = discontinuous_weights(p, [(12.4, 12.6)], [1], outside="clamp")
    np.testing.assert_allclose(w, [0.75, 0.25, 0.0])  # the part below 12.5 uses the end frame
    with pytest.raises(InputError, match="one share per range"):
        discontinuous_weights(p, [(12.5, 12.6)], [1, 2])
    with pytest.raises(InputError, match="fractions"):
        discontinuous_weights(p, [(12.5, 12.6)], [0])
    with pytest.raises(InputError, match="empty"):
        discontinuous_weights([], [(12.5, 12.6)], [1])


@settings(max_examples=60, deadline=None)
@given(positions_st.filter(lambda p: len(set(p)) > 1), st.lists(st.floats(0, 1), min_size=1,
                                                                 max_size=20))
def test_row_weights_reproduce_each_rows_position(p, fractions):
    lo, hi = min(p), max(p)
    targets = lo + np.array(fractions) * (hi - lo)
    w = row_weights(p, targets)
    assert w.shape == (targets.size, len(p))
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w @ np.asarray(p), targets, atol=1e-12)  # weighted mean = p_r
    # only the frames around p_r (within one frame spacing) are used
    gaps = np.diff(np.unique(p)).max()
    far = np.abs(np.asarray(p)[None, :] - targets[:, None]) > gaps
    assert np.all(w[far] == 0)


def test_row_weights_window_is_a_short_sweep():
    p = np.linspace(12.5, 12.8, 13)
    targets = np.array([12.56, 12.6, 12.711])
    w = row_weights(p, targets, window_mm=0.05)
    expected = np.stack([_interp_time_shares(p, t - 0.025, t + 0.025) for t in targets])
    np.testing.assert_allclose(w, expected, atol=1e-4)
    np.testing.assert_allclose(w @ p, targets, atol=1e-12)


def test_row_weights_outside():
    with pytest.raises(InputError, match="outside"):
        row_weights([12.5, 12.6], [12.7])
    np.testing.assert_array_equal(row_weights([12.5, 12.6], [12.7], outside="clamp"), [[0, 1]])
    np.testing.assert_array_equal(row_weights([12.6], [12.6]), [[1.0]])


# ----------------------------------------------------------------------------- flexdof dof
@pytest.fixture
def ramp_stack(tmp_path):
    """9 constant frames whose value is their image distance minus 12.5 mm."""
    positions = np.linspace(12.52, 12.84, 9)
    lines = ['lens = "fujinon-12.5mm-f1.4-sony-1-3in"', 'kind = "focal-stack"']
    for i, p in enumerate(positions):
        write.write_image(tmp_path / f"f{i}.tif", np.full((24, 32), p - 12.5, np.float32),
                       encoding="float32")
        lines += ["[[frames]]", f'file = "f{i}.tif"', f"image_distance_mm = {float(p)!r}"]
    (tmp_path / "stack.toml").write_text("\n".join(lines) + "\n")
    return tmp_path, positions


def test_dof_tilted_rows_focus_on_the_plane(ramp_stack):
    directory, _ = ramp_stack
    out = directory / "tilt.tif"
    assert cli.main([
        "dof", str(directory), "-o", str(out), "--tilt-deg", "50", "--at-mm", "750",
        "--align", "none", "--float",
    ]) == 0
    result = read.read_frame(out)
    # independent: each row's chief ray meets the plane u = U + Y tan(phi)
    lens_h = 768 * 4.65e-3
    y = (np.arange(24) - 11.5) * lens_h / 24
    f, big_u, k = 12.5, 750.0, math.tan(math.radians(50))
    u = (big_u + y * k) / (1 + y * k / f)
    expected = f * u / (u - f) - 12.5
    np.testing.assert_allclose(result[:, 7], expected, atol=2e-6)
    assert (directory / "tilt.tif.json").is_file()  # the same sidecar naming as stack


def test_dof_rows_csv_and_in_focus(ramp_stack, tmp_path):
    directory, _ = ramp_stack
    rows_csv = tmp_path / "rows.csv"
    rows_csv.write_text("row,depth_mm\n0,600\n23,1200\n")
    out = directory / "rows.tif"
    assert cli.main(["dof", str(directory), "-o", str(out), "--rows", str(rows_csv),
                     "--align", "none", "--float"]) == 0
    v = [optics.image_distance(12.5, d) for d in (600.0, 1200.0)]
    expected = np.interp(np.arange(24), [0, 23], v) - 12.5
    np.testing.assert_allclose(read.read_frame(out)[:, 0], expected, atol=2e-6)

    out2 = directory / "two.tif"
    assert cli.main(["dof", str(directory), "-o", str(out2), "--in-focus", "500:600",
                     "--in-focus", "2000:2000", "--fraction", "3", "--fraction", "1",
                     "--align", "none", "--float"]) == 0
    lo, hi = (optics.image_distance(12.5, d) for d in (600.0, 500.0))
    pause = optics.image_distance(12.5, 2000.0)
    # mean position of the emulated motion: 3/4 sweeping [lo, hi], 1/4 paused
    expected_value = 0.75 * 0.5 * (lo + hi) + 0.25 * pause - 12.5
    np.testing.assert_allclose(read.read_frame(out2), expected_value, atol=2e-6)


def test_dof_errors(ramp_stack, capsys):
    directory, _ = ramp_stack
    out = str(directory / "x.tif")
    assert cli.main(["dof", str(directory), "-o", out]) == 2
    assert "exactly one DOF target" in capsys.readouterr().err
    assert cli.main(["dof", str(directory), "-o", out, "--tilt-deg", "10"]) == 2
    assert "--at-mm" in capsys.readouterr().err
    assert cli.main(["dof", str(directory), "-o", out, "--in-focus", "600-500"]) == 2
    assert "NEAR:FAR" in capsys.readouterr().err
    assert cli.main(["dof", str(directory), "-o", out, "--in-focus", "300:400"]) == 2
    err = capsys.readouterr().err
    assert "--in-focus 300:400: outside the stack's focus range 472.1:7825.0 mm" in err
    assert "outside=" not in err  # names the CLI flag, not the API argument


def test_row_offsets_tile_the_sensor():
    y = motion.row_offsets_mm(4, 4.0)
    np.testing.assert_allclose(y, [-1.5, -0.5, 0.5, 1.5])


@pytest.mark.parametrize(
    "p", [[12.5, 12.6, 12.7, 12.8], [12.8, 12.5, 12.55, 12.7], [12.5, 12.5, 12.6, 12.9]]
)
def test_full_ends_emulate_a_sweep_half_a_spacing_beyond_the_end_frames(p):
    """Sample a sweep over [p0 - d0/2, pn + dn/2]; each instant counts for its nearest frame."""
    w = constant_speed_weights(p, ends="full")
    q = np.unique(p)
    lo, hi = q[0] - (q[1] - q[0]) / 2, q[-1] + (q[-1] - q[-2]) / 2
    times = np.linspace(lo, hi, 200_001)
    nearest = np.abs(times[:, None] - np.asarray(p)[None, :])
    owners = nearest == nearest.min(axis=1, keepdims=True)
    share = (owners / owners.sum(axis=1, keepdims=True)).mean(axis=0)
    np.testing.assert_allclose(w, share, atol=1e-4)
    assert w.sum() == pytest.approx(1.0)


def test_full_ends_give_equal_weights_for_even_spacing():
    np.testing.assert_allclose(constant_speed_weights(np.linspace(12.5, 12.9, 7), ends="full"),
                               np.full(7, 1 / 7))
    with pytest.raises(InputError, match="ends"):
        constant_speed_weights([1.0, 2.0], ends="both")


# ----------------------------------------------------------------------------- mutation kills
def test_weights_validate_their_inputs():
    nan = float("nan")
    with pytest.raises(InputError, match="finite"):
        constant_speed_weights([12.5, nan])
    with pytest.raises(InputError, match="empty"):
        constant_speed_weights([])
    p = [12.5, 12.6, 12.7]
    for bad in ([12.5, 12.6], [(12.5, 12.6, 12.7)], [(12.55,)], np.zeros((0, 2)),
                np.full((1, 2, 2), 12.55)):
        with pytest.raises(InputError, match="pairs"):
            discontinuous_weights(p, bad, [1])
    with pytest.raises(InputError, match="ranges_image_mm must be finite"):
        discontinuous_weights(p, [(12.5, nan)], [1])
    with pytest.raises(InputError, match="1 ranges, 2 fractions"):
        discontinuous_weights(p, [(12.5, 12.6)], [1, 2])
    with pytest.raises(InputError, match="2 ranges, 1 fractions"):
        discontinuous_weights(p, [(12.5, 12.6), (12.6, 12.7)], [1])
    for bad in ([nan], [-1.0], [1.0, 0.0]):
        with pytest.raises(InputError, match="fractions must be finite and > 0"):
            discontinuous_weights(p, [(12.5, 12.6)] * len(bad), bad)
    with pytest.raises(InputError, match="outside must be"):
        discontinuous_weights(p, [(12.5, 12.6)], [1], outside="none")
    with pytest.raises(InputError, match=r"reaches 12\.75\.\.12\.8 mm, .* \[12\.5, 12\.7\] mm"):
        row_weights(p[::-1], [12.6, 12.8, 12.75])
    for bad in ([[12.6]], 12.6, [], [nan], [12.6, nan]):
        with pytest.raises(InputError, match="row_positions_mm must be a non-empty 1-D"):
            row_weights(p, bad)
    for bad in (-0.01, float("inf"), nan, "0.1", None):
        with pytest.raises(InputError, match="window_mm"):
            row_weights(p, [12.6], window_mm=bad, outside="clamp")


def test_row_windows_must_fit_inside_the_stack_at_both_ends():
    p = [12.5, 12.6, 12.7]
    for target in (12.51, 12.69):  # the target is inside, its +-0.02 window is not
        with pytest.raises(InputError, match="outside"):
            row_weights(p, [target], window_mm=0.04)
        assert row_weights(p, [target], window_mm=0.02).shape == (1, 3)
    # clamped, the part of the window beyond the last frame uses the last frame
    w = row_weights(p, [12.69], window_mm=0.04, outside="clamp")
    # [12.67, 12.7]: mean hat of 12.6 = 0.5 (0.3 + 0) * 0.03 / 0.04; of 12.7 the rest
    np.testing.assert_allclose(w, [[0.0, 0.1125, 0.8875]], atol=1e-12)


def test_targets_a_rounding_error_beyond_the_ends_are_accepted():
    p = [12.5, 12.6, 12.7]  # tolerance 1e-9 of the largest position: 12.7 nm here
    w = row_weights(p, [12.5 - 5e-9, 12.7 + 5e-9])
    np.testing.assert_allclose(w, [[1, 0, 0], [0, 0, 1]], atol=1e-6)
    for beyond in (12.5 - 5e-8, 12.7 + 5e-8):
        with pytest.raises(InputError, match="outside"):
            row_weights(p, [beyond])


def test_whole_millimetre_windows_are_sweeps_too():
    p = np.linspace(10.0, 14.0, 9)  # any unit linear in the image distance
    for window in (1.0, 2.0):
        w = row_weights(p, [12.0, 12.3], window_mm=window)
        expected = np.stack([_interp_time_shares(p, t - window / 2, t + window / 2)
                             for t in (12.0, 12.3)])
        np.testing.assert_allclose(w, expected, atol=1e-4)
