"""Accuracy-vs-time benchmark: Pareto analysis on hand-made cases, the reference kernel."""

from __future__ import annotations

import numpy as np

from pipeline.core import psf
from pipeline.core.motion import constant_speed
from pipeline.io import profiles
from pipeline.paper import bench
from pipeline.paper.bench.pareto import Row
from pipeline.paper.bench.scenes import REFERENCE_THETA_ORDER, SEC41_LENS


def row(setting, value, time_s, *, default=False, metric="psnr_db", requires="", knob="k"):
    return Row("g", knob, "scene", setting, default, metric, value, time_s, requires)


# ----------------------------------------------------------------------------- hand-made
def test_pareto_front_hand_made():
    times = [1.0, 2.0, 3.0, 2.5, 0.5, 3.0]
    errors = [5.0, 3.0, 1.0, 4.0, 9.0, 1.0]
    # (2.5, 4) is beaten by (2, 3); the two (3, 1) tie: neither dominates the other.
    expected = [True, True, True, False, True, True]
    assert bench.pareto_front(times, errors).tolist() == expected


def test_dominated_defaults_needs_both_margins():
    d = row("default", 30.0, 1.0, default=True)
    rows = [
        d,
        row("slower, better", 32.0, 2.0),
        row("faster, same", 30.1, 0.1),  # 0.1 dB is inside the 0.2 dB margin
        row("a bit faster, better", 31.0, 0.9),  # 10% faster is inside the 20% margin
        row("fast, worse", 20.0, 0.01),
    ]
    assert bench.dominated_defaults(rows) == []
    winner = row("faster and better", 30.5, 0.5)
    assert bench.dominated_defaults([*rows, winner]) == [(d, winner)]


def test_dominated_defaults_orientation_and_requires():
    d = row("default", 1e-2, 1.0, default=True, metric="kernel_l1")
    better = row("better", 1e-3, 0.5, metric="kernel_l1")
    worse = row("worse", 1e-1, 0.5, metric="kernel_l1")
    assert bench.dominated_defaults([d, worse]) == []
    assert bench.dominated_defaults([d, better]) == [(d, better)]
    # relative margin: 20% lower error is not "clearly" lower (25% needed)
    assert bench.dominated_defaults([d, row("close", 0.8e-2, 0.5, metric="kernel_l1")]) == []
    cond = row("needs positions", 0.0, 0.1, metric="kernel_l1", requires="positions")
    assert bench.dominated_defaults([d, cond]) == []
    assert bench.dominated_defaults([d, cond], conditional=True) == [(d, cond)]
    # other knobs and scenes never compete with a default
    other = row("other knob", 1e-6, 1e-3, metric="kernel_l1", knob="other")
    assert bench.dominated_defaults([d, other]) == []


def test_ipsf_reference_agrees_with_fine_numeric_quadrature():
    """The benchmark's reference kernel vs an independent route: Eq. 5 over time."""
    lens = profiles.load_lens(SEC41_LENS)
    sweep = constant_speed(12.5, 1.0, 0.36)
    ref = psf.integrated_psf(lens, 750.0, sweep, theta_order=REFERENCE_THETA_ORDER)
    fine = psf.integrated_psf(lens, 750.0, sweep, method="numeric", time_order=8, time_step_px=0.1)
    assert np.abs(ref - fine).sum() < 1e-5


# The --quick run end to end and the timing checks live in
# tests/benchmarks/bench_accuracy_quick.py (timings on a shared machine are not unit tests).
