"""The accuracy benchmark's rows and metrics, the Pareto front of (time, error), and
which defaults another setting dominates.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Sequence

import numpy as np


# ----------------------------------------------------------------------------- records
def default_of(function, parameter: str):
    """The default of a keyword parameter, read from the code (so the bench marks the real one)."""
    return inspect.signature(function).parameters[parameter].default


@dataclasses.dataclass(frozen=True)
class Metric:
    """How an error metric is read: direction, unit and what counts as a clear difference.

    ``b`` is clearly more accurate than ``a`` when it is better by more than
    ``max(margin_rel * |a|, margin_abs)``.
    """

    label: str
    higher_is_better: bool
    margin_abs: float
    margin_rel: float = 0.0


METRICS = {
    "psnr_db": Metric("PSNR vs ground truth, dB (higher is better)", True, 0.2),
    "kernel_l1": Metric("kernel L1 vs reference (lower is better)", False, 1e-4, 0.25),
    "rel_rms": Metric("render RMS error / RMS contrast (lower is better)", False, 2e-4, 0.25),
    "corner_px": Metric("corner reprojection error, px (lower is better)", False, 0.05, 0.25),
    "eq8_spread": Metric("Eq. 8 spread of per-depth kernels (lower is better)", False, 1e-3, 0.25),
}


@dataclasses.dataclass(frozen=True)
class Row:
    """One measured setting of one knob: its error (``metric`` = ``value``) and time."""

    group: str
    knob: str
    scene: str
    setting: str
    is_default: bool
    metric: str
    value: float
    time_s: float
    requires: str = ""
    note: str = ""


@dataclasses.dataclass(frozen=True)
class Config:
    """What to sweep (``Config.quick()`` for CI, ``Config.full()`` for the report)."""

    repeats: int
    shape: tuple[int, int]
    frames: int
    truth_tolerance: float
    ipsf_depths_mm: tuple[float, ...]
    theta_orders: tuple[int, ...]
    time_orders: tuple[int, ...]
    time_steps_px: tuple[float, ...]
    size_fractions: tuple[float, ...]
    tolerances: tuple[float, ...]
    align_sides_px: tuple[int, ...]
    rl_iterations: tuple[int, ...]
    sparse_iterations: tuple[int, ...]
    regularization_factors: tuple[float, ...]
    tiles_px: tuple[int, ...]
    overlap_fractions: tuple[float, ...]
    frame_counts: tuple[int, ...]
    deconvolution_scenes: tuple[str, ...]

    @classmethod
    def quick(cls) -> Config:
        return cls(
            repeats=2,
            shape=(120, 180),
            frames=8,
            truth_tolerance=2e-4,
            ipsf_depths_mm=(450.0, 750.0, 2000.0),
            theta_orders=(2, 4, 8, 16),
            time_orders=(2, 6),
            time_steps_px=(2.0, 0.5),
            size_fractions=(0.5, 0.75, 1.0),
            tolerances=(1e-2, 3e-3, 1e-3),
            align_sides_px=(192, 768),
            rl_iterations=(10, 30),
            sparse_iterations=(20, 50),
            regularization_factors=(0.3, 1.0, 3.0),
            tiles_px=(64, 1024),
            overlap_fractions=(0.5, 1.0),
            frame_counts=(4, 8),
            deconvolution_scenes=("motorcycle", "edges-noisy"),
        )

    @classmethod
    def full(cls) -> Config:
        return cls(
            repeats=3,
            shape=(192, 288),
            frames=8,
            truth_tolerance=1e-4,
            ipsf_depths_mm=(450.0, 600.0, 750.0, 1000.0, 1500.0, 2000.0),
            theta_orders=(2, 3, 4, 6, 8, 12, 16, 32),
            time_orders=(1, 2, 3, 4, 6, 8),
            time_steps_px=(4.0, 2.0, 1.0, 0.5, 0.25),
            size_fractions=(0.25, 0.5, 0.75, 0.9, 1.0),
            tolerances=(3e-2, 1e-2, 3e-3, 1e-3, 3e-4),
            align_sides_px=(192, 256, 384, 768),
            rl_iterations=(10, 30, 100),
            sparse_iterations=(20, 50, 100),
            regularization_factors=(0.1, 0.3, 1.0, 3.0, 10.0),
            tiles_px=(64, 128, 256, 1024),
            overlap_fractions=(0.25, 0.5, 1.0),
            frame_counts=(3, 4, 6, 8, 12, 16),
            deconvolution_scenes=("motorcycle", "edges-clean", "edges-noisy"),
        )


# ----------------------------------------------------------------------------- Pareto
def oriented(row: Row) -> float:
    """The row's error with lower = better (PSNR is negated)."""
    return -row.value if METRICS[row.metric].higher_is_better else row.value


def pareto_front(times: Sequence[float], errors: Sequence[float]) -> np.ndarray:
    """Mask of the points no other point beats in both time and error (lower is better).

    A point is dominated when another is at least as good in both and strictly
    better in one.
    """
    t, e = np.asarray(times, float), np.asarray(errors, float)
    front = np.ones(t.size, dtype=bool)
    for i in range(t.size):
        better_eq = (t <= t[i]) & (e <= e[i])
        strictly = (t < t[i]) | (e < e[i])
        front[i] = not np.any(better_eq & strictly)
    return front


def clearly_better(candidate: Row, default: Row) -> bool:
    """Is ``candidate`` more accurate than ``default`` by more than the metric's margin?"""
    m = METRICS[default.metric]
    gain = oriented(default) - oriented(candidate)
    return gain > max(m.margin_rel * abs(default.value), m.margin_abs)


def dominated_defaults(
    rows: Sequence[Row], *, time_margin: float = 0.2, conditional: bool = False
) -> list[tuple[Row, Row]]:
    """``(default, better)`` pairs: a setting faster by > ``time_margin`` and clearly better.

    Compared within one (knob, scene, metric). Settings with ``requires`` (they need
    information the default does without) count only with ``conditional=True``.
    """
    found = []
    for _, group in _groups(rows, ("knob", "scene", "metric")):
        defaults = [r for r in group if r.is_default]
        if len(defaults) != 1:
            continue
        d = defaults[0]
        for r in group:
            if r is d or (r.requires and not conditional):
                continue
            if r.time_s < (1 - time_margin) * d.time_s and clearly_better(r, d):
                found.append((d, r))
    return found


def _groups(rows: Sequence[Row], keys: Sequence[str]):
    order: dict[tuple, list[Row]] = {}
    for r in rows:
        order.setdefault(tuple(getattr(r, k) for k in keys), []).append(r)
    return list(order.items())
