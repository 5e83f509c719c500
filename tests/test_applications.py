"""The paper's four applications (Figs. 6, 10, 11, 12) on synthetic scenes: the measures
against closed forms, the banded rolling-shutter render against the simulator's, and
each application's claim on its render."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from pipeline import cli
from pipeline.core import motion, optics, simulate
from pipeline.core.scene import Camera
from pipeline.io.profiles import load_lens
from pipeline.paper import applications as A


def _sinusoid(freq: float, shape=(96, 96)) -> np.ndarray:
    cols = np.arange(shape[1])
    return np.tile(0.5 + 0.3 * np.cos(2 * np.pi * freq * cols), (shape[0], 1))


@pytest.mark.parametrize("cycles", [8, 14, 24])
@pytest.mark.parametrize("sigma", [0.6, 1.2])
def test_detail_transfer_of_a_blurred_sinusoid_is_its_attenuation(cycles, sigma):
    sharp = _sinusoid(cycles / 96)
    blurred = ndimage.gaussian_filter(sharp, sigma, mode="wrap")
    mask = np.zeros(sharp.shape, bool)
    mask[16:-16, 16:-16] = True
    # independent: the amplitude of the sinusoid's DFT bin before and after the blur
    expected = abs(np.fft.rfft(blurred[0])[cycles]) / abs(np.fft.rfft(sharp[0])[cycles])
    assert A.detail_transfer(blurred, sharp, mask, register=False) == pytest.approx(
        expected, abs=0.01
    )


def test_detail_transfer_registers_a_shift_and_ignores_noise():
    rng = np.random.default_rng(1)
    sharp = ndimage.gaussian_filter(rng.random((128, 128)), 0.8)
    shifted = ndimage.shift(sharp, (0.0, 1.5), order=3, mode="wrap")
    noisy = shifted + rng.normal(0, 0.05, shifted.shape)
    mask = np.zeros(sharp.shape, bool)
    mask[20:-20, 20:-20] = True
    assert A.detail_shift(noisy, sharp, mask) == pytest.approx((0.0, 1.5), abs=0.1)
    assert A.detail_transfer(noisy, sharp, mask) == pytest.approx(1.0, abs=0.05)
    assert A.detail_transfer(noisy, sharp, mask, register=False) < 0.5


def test_scaled_lens_keeps_the_sensor_and_the_readout():
    lens = load_lens(A.ROLLING_LENS)
    small = A.scaled_lens(lens, 432)
    assert (small.width_px, small.height_px) == (432, 324)
    assert small.sensor_height_mm == pytest.approx(lens.sensor_height_mm)
    assert small.readout_time_s == pytest.approx(lens.readout_time_s)


def test_table_depths_focus_where_the_tilted_planner_puts_the_detector():
    lens = A.scaled_lens(load_lens(A.ROLLING_LENS), 216)
    u = A.table_depths(lens, 53.0, 450.0)
    y = motion.row_offsets_mm(lens.height_px, lens.sensor_height_mm)
    p = motion.tilted_row_image_distances(lens.focal_length_mm, 53.0, 450.0, y)
    np.testing.assert_allclose(optics.image_distance(lens.focal_length_mm, u), p, rtol=1e-12)


def test_banded_rolling_render_matches_the_simulators():
    lens = A.scaled_lens(load_lens(A.ROLLING_LENS), 64)
    scene, _, _, _, _ = A.tilted_scene(lens)
    camera = Camera(
        lens, motion.plan_tilted_dof(lens, 53.0, 450.0, exposure_s=0.03), row_exposure_s=0.03
    )
    reference = simulate.render(
        scene, camera, plan_=simulate.plan(scene, camera, magnification_steps=0, per_row=True)
    )
    ours = A.render_rolling(scene, camera, band_rows=1)
    assert np.sqrt(np.mean((ours - reference) ** 2)) < 0.01 * reference.std()


def test_edof_is_uniform_over_depth_after_deconvolution():
    app = A.edof_application()
    s = app.summary
    assert s["detail spread edof"] < 0.4 * s["detail spread f1.4"]
    assert s["detail min edof"] > 0.7 > s["detail min f1.4"] + 0.3
    assert s["detail min edof"] > s["detail min capture"] + 0.3  # deconvolution restores
    assert s["noise mean edof"] < 0.6 * s["noise mean f8"]  # Fig. 6(d) is much noisier
    assert s["detail min f8"] > 0.9


def test_discontinuous_dof_erases_the_mesh_and_keeps_toys_and_backdrop():
    app = A.discontinuous_application()
    by = {r["camera"]: r for r in app.rows}
    assert by["flexible"]["mesh contrast"] < 0.3 * by["f8"]["mesh contrast"]
    for region in ("detail toys", "detail backdrop"):
        assert by["flexible"][region] > 0.4
    # a normal f/1.4 camera on the toys loses the backdrop; the flexible one does not
    assert by["flexible"]["detail backdrop"] > 4 * by["f1.4 near"]["detail backdrop"]


def test_tilted_dof_is_sharp_along_the_table_and_at_the_mugs_base_only():
    app = A.tilted_application()
    s = app.summary
    assert s["table detail spread tilted"] < 0.1 < 0.4 < s["table detail spread normal"]
    assert s["table detail min tilted"] > 0.85 > 0.5 > s["table detail min normal"]
    assert s["mug bottom detail tilted"] > 0.85
    assert s["mug top detail tilted"] < 0.6


def test_nonplanar_dof_follows_the_crayons_and_defocuses_the_tag():
    app = A.nonplanar_application(width_px=432)
    s = app.summary
    assert s["crayon detail min curved"] > 0.9
    assert s["tag detail curved"] < 0.8 < s["tag detail normal"]
    assert s["crayon detail min normal"] < 0.8


def test_cli_writes_an_application(tmp_path):
    assert cli.main(["figures", "--only", "12", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "fig12_nonplanar.png").stat().st_size > 0
    text = (tmp_path / "applications.md").read_text()
    assert "price tag" in text and "Fig. 12" in text
