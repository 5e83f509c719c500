"""The paper's figures: magnified IPSFs (Fig. 5c), dissimilarity matrices (Fig. 5),
MTFs and the noise/DOF table (Fig. 9), and the files ``flexdof figures`` writes."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from pipeline import cli
from pipeline.core import optics, psf, spectra
from pipeline.io.profiles import load_lens
from pipeline.paper import figures

LENS = load_lens(figures.LENS)


@pytest.fixture(scope="module")
def matrices():
    return figures.fig5_matrices(LENS, size=61)


def test_shifted_ipsf_at_the_centre_is_the_closed_form_ipsf():
    kernel = figures.shifted_ipsf(LENS, 750.0, figures.edof_profile(), 0.0, size=61)
    reference = psf.integrated_psf(LENS, 750.0, figures.edof_profile(), model="pillbox",
                                   size=61, method="analytic")
    assert np.abs(kernel - reference).max() < 1e-3 * reference.max()


@pytest.mark.parametrize("offset", [256.0, 512.0])
def test_shifted_ipsf_moves_with_the_magnification(offset):
    profile = figures.edof_profile()
    kernel = figures.shifted_ipsf(LENS, 750.0, profile, offset, size=61)
    v = optics.image_distance(12.5, 750.0)
    # independent: the chief ray lands at x p/v; averaged over a constant-speed sweep
    mean_shift = offset * (0.5 * (profile.start_mm + profile.end_mm) - v) / v
    x = np.arange(-30, 31)
    assert kernel.sum() == pytest.approx(1.0)
    assert (kernel.sum(axis=0) @ x) == pytest.approx(mean_shift, abs=0.02)
    assert (kernel.sum(axis=1) @ x) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(kernel, kernel[::-1], atol=1e-15)  # symmetric about the row


def test_fig5_edof_ipsfs_are_alike_over_depth(matrices):
    for m in matrices.values():
        np.testing.assert_allclose(m, m.T)
        np.testing.assert_array_equal(np.diag(m), 0)
    off = ~np.eye(5, dtype=bool)
    normal, edof, pos = (matrices[k][off] for k in ("normal-depth", "edof-depth", "edof-position"))
    assert np.median(normal) > 50 * np.median(edof)
    assert normal.max() > 100 * edof.max()
    assert pos.max() < edof.max()  # 5c: magnification matters less than depth


def test_fig9_mtf_k2_keeps_more_high_frequencies():
    kernels = figures.fig9_kernels(LENS, size=61)
    freq, m1 = spectra.mtf(kernels["k1"])
    _, m2 = spectra.mtf(kernels["k2"])
    high = (freq > 0.1) & (freq < 0.5)
    assert np.all(m2[high] > m1[high])


def test_fig9_table_reproduces_the_papers_claim():
    rows = {r["camera"]: r for r in figures.fig9_table(LENS, figures.natural_image())}
    sigma_index = figures.SIGMAS.index(0.01)
    k1 = rows["EDOF k1"]["noise"][sigma_index]
    # Sec. 4.3: at sigma = 0.01, EDOF k1 has about the SNR of a normal camera at f/2.8 ...
    assert rows["normal f/2"]["noise"][sigma_index] < k1 < rows["normal f/4"]["noise"][sigma_index]
    assert figures.equivalent_f_number(k1, 0.01) == pytest.approx(2.8, abs=0.4)
    # ... and more DOF than f/8
    assert rows["EDOF k1"]["near_mm"] < rows["normal f/8"]["near_mm"]
    assert math.isinf(rows["EDOF k1"]["far_mm"])
    # the SNR benefit grows with the noise level: the noise amplification falls
    ratios = [e / s for e, s in zip(rows["EDOF k1"]["noise"], figures.SIGMAS)]
    assert all(a > b for a, b in itertools.pairwise(ratios))
    # k2 sweeps half as far: less noise, less DOF
    assert all(a < b for a, b in zip(rows["EDOF k2"]["noise"], rows["EDOF k1"]["noise"]))
    assert rows["EDOF k2"]["near_mm"] > rows["EDOF k1"]["near_mm"]
    # normal cameras: DOF from Eq. 2 with c = 14.1 um grows as the aperture closes
    nears = [rows[f"normal f/{n:g}"]["near_mm"] for n in figures.F_NUMBERS]
    assert all(a > b for a, b in itertools.pairwise(nears))


def test_render_fig3_and_the_cli(tmp_path):
    assert cli.main(["figures", "--out", str(tmp_path), "--only", "3"]) == 0
    png = tmp_path / "fig3_psf_profiles.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    lines = (tmp_path / "fig3_psf_profiles.csv").read_text().splitlines()
    assert len(lines) == 1 + 4 * 5  # header + 2 models x 2 cameras x 5 depths


def test_psf_vs_ipsf_figure(tmp_path):
    out = figures.psf_vs_ipsf_figure(LENS, figures.edof_profile(), tmp_path / "p.png")
    assert out.read_bytes()[:4] == b"\x89PNG"
