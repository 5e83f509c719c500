"""Accuracy-vs-time benchmark: Pareto analysis on hand-made cases, the --quick run end to end."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from PIL import Image

from pipeline.cli import main as cli_main
from pipeline.core import psf
from pipeline.core.motion import constant_speed
from pipeline.io import profiles
from pipeline.paper import bench
from pipeline.paper.bench.pareto import Row, _groups
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


def test_best_times_takes_the_minimum_and_keeps_results():
    calls = {"slow": 0, "fast": 0}

    def slow():
        calls["slow"] += 1
        time.sleep(0.06)
        return "s"

    def fast():
        calls["fast"] += 1
        time.sleep(0.002)
        return "f"

    (t_slow, r_slow), (t_fast, r_fast) = bench.best_times([slow, fast], 3)
    assert (r_slow, r_fast) == ("s", "f")
    assert 0.06 <= t_slow < 0.5 and 0.002 <= t_fast < t_slow
    assert calls["slow"] == 3 and calls["fast"] > 3  # short calls are looped per sample


def test_ipsf_reference_agrees_with_fine_numeric_quadrature():
    """The benchmark's reference kernel vs an independent route: Eq. 5 over time."""
    lens = profiles.load_lens(SEC41_LENS)
    sweep = constant_speed(12.5, 1.0, 0.36)
    ref = psf.integrated_psf(lens, 750.0, sweep, theta_order=REFERENCE_THETA_ORDER)
    fine = psf.integrated_psf(lens, 750.0, sweep, method="numeric", time_order=8, time_step_px=0.1)
    assert np.abs(ref - fine).sum() < 1e-5


# ----------------------------------------------------------------------------- quick run
@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("accuracy")
    start = time.perf_counter()
    assert cli_main(["bench", "accuracy", "--quick", "--out", str(out)]) == 0
    return out, time.perf_counter() - start


def test_quick_run_outputs_are_well_formed(quick_run):
    out, elapsed = quick_run
    assert elapsed < 150, f"--quick took {elapsed:.0f} s (budget 2 min)"
    rows = bench.read_table(out / "accuracy.csv")
    groups = {r.group for r in rows}
    assert groups == {"ipsf", "simulation", "alignment", "deconvolution", "stack sampling"}
    for r in rows:
        assert r.metric in bench.METRICS
        assert math.isfinite(r.value) and math.isfinite(r.time_s) and r.time_s > 0, r
    for (knob, scene, metric), group in _groups(rows, ("knob", "scene", "metric")):
        n_default = sum(r.is_default for r in group)
        expected = 0 if knob.startswith("frames over") else 1
        assert n_default == expected, (knob, scene, metric)
        assert len(group) >= 2, (knob, scene, metric)
    table = (out / "accuracy.md").read_text().splitlines()
    assert len(table) == len(rows) + 2 and table[0].startswith("| knob |")
    with Image.open(out / "pareto.png") as im:
        assert im.format == "PNG" and im.size[0] > 800 and im.size[1] > 600
    summary = (out / "summary.md").read_text()
    assert "## Defaults" in summary and "sparse-prior deconvolution buys" in summary


def test_quick_run_errors_behave(quick_run):
    """Sanity of the measured errors: they move the way the physics says."""
    rows = bench.read_table(quick_run[0] / "accuracy.csv")

    def value(knob, setting, scene=None, metric=None):
        found = [
            r
            for r in rows
            if r.knob == knob
            and r.setting == setting
            and (scene is None or r.scene == scene)
            and (metric is None or r.metric == metric)
        ]
        assert len(found) == 1, (knob, setting, scene, found)
        return found[0].value

    theta = [value("pixel-integration order (analytic)", f"{n} nodes") for n in (2, 4, 8, 16)]
    assert theta == sorted(theta, reverse=True) and theta[2] < 1e-6
    tol = [value("layer tolerance", t) for t in ("0.01", "0.003", "0.001")]
    assert tol == sorted(tol, reverse=True) and tol[-1] < 1e-3
    assert value("occlusion", "off") > 10 * value("occlusion", "auto (on: depth edges)")
    for scene in ("motorcycle", "edges-noisy"):
        none = value("alignment (corner error)", "none", scene)
        assert value("alignment (corner error)", "estimate @768 px", scene) < 0.5 * none
        assert value("alignment (corner error)", "analytic", scene) < 1e-9


def test_quick_run_default_matches_the_engine(quick_run):
    """The benchmark's default deconvolution reproduces `flexdof stack` (same PSNR)."""
    rows = bench.read_table(quick_run[0] / "accuracy.csv")
    for scene in ("motorcycle", "edges-noisy"):
        engine_row = [
            r
            for r in rows
            if r.knob == "alignment (final PSNR)" and r.scene == scene and r.is_default
        ]
        bench_row = [r for r in rows if r.knob == "method" and r.scene == scene and r.is_default]
        assert engine_row[0].value == pytest.approx(bench_row[0].value, abs=1e-3)


def test_quick_run_defaults_are_on_the_pareto_front(quick_run):
    """No setting is >20% faster AND clearly more accurate than its knob's default."""
    rows = bench.read_table(quick_run[0] / "accuracy.csv")
    dominated = bench.dominated_defaults(rows, time_margin=0.2)
    assert not dominated, "\n".join(
        f"{d.knob} ({d.scene}): default {d.setting} {d.value:.4g} in {d.time_s:.3g} s; "
        f"{r.setting} {r.value:.4g} in {r.time_s:.3g} s"
        for d, r in dominated
    )
