"""Committed reference arrays for the numerical cores (``tests/data/reference``).

A deconvolution may improve, never regress: its PSNR against the sharp scene must
stay within 0.05 dB of the stored output's (a fraction of a dB is caught, which the
+1 dB quality thresholds cannot see). The IPSF is stored to 1e-9. Regenerate with
``python tests/data/reference/make_references.py`` only for an intended change.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.core import deconvolve as dc
from pipeline.core import psf
from pipeline.core.motion import constant_speed
from pipeline.io.profiles import load_lens

REF = Path(__file__).resolve().parent / "data" / "reference"
METHODS = {
    "wiener": {"noise_sigma": 2e-3},
    "rl": {"iterations": 40, "noise_sigma": 2e-3},
    "sparse": {"iterations": 40, "noise_sigma": 2e-3},
}


def psnr(a, b, m=4) -> float:
    err = np.mean((np.asarray(a, float) - b)[m:-m, m:-m] ** 2)
    return float(10 * np.log10(1.0 / err))


@pytest.mark.parametrize("method", list(METHODS))
def test_deconvolution_does_not_regress_against_its_reference(method):
    data = np.load(REF / "comet_input.npz")
    sharp = data["sharp"].astype(float)
    ref = np.load(REF / f"comet_{method}.npz")["restored"]
    out = dc.deconvolve(data["blurred"], data["kernel"], method=method, **METHODS[method])
    reference_db, now_db = psnr(ref, sharp), psnr(out, sharp)
    assert reference_db > psnr(data["blurred"], sharp) + 3  # the reference itself restores
    assert now_db >= reference_db - 0.05, f"{method}: {now_db:.3f} dB < {reference_db:.3f} dB"


@pytest.mark.parametrize("depth", [450.0, 750.0])
def test_sec41_ipsf_matches_its_reference(depth):
    lens = load_lens("fujinon-12.5mm-f1.4-sony-1-3in")
    kernel = psf.integrated_psf(lens, depth, constant_speed(12.5, 1.0, 0.36), size=31)
    ref = np.load(REF / "ipsf_sec41.npz")[f"u{int(depth)}"]
    assert np.abs(kernel - ref).sum() < 1e-9
