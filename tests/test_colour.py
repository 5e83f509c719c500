"""The colour helpers (:mod:`pipeline.core.colour`) on the inputs a deconvolution makes:
values outside [0, 1] through the sRGB transfer functions, element by element against the
standard's formulas in Python floats, and a grey image moved below 0 (stop 55's mutation
run: the covering tests kept to [0, 1] and to positive targets)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from pipeline.core.colour import linear_to_srgb, mean_grey, move_grey, srgb_to_linear

# undershoots and overshoots of a deconvolved image, both knees, and the ends of the range
VALUES = [-0.5, -0.06, -0.001, 0.0, 0.002, 0.0031308, 0.004, 0.04045, 0.05, 0.5, 1.0, 1.7]


def _eotf(c: float) -> float:
    """IEC 61966-2-1's decoding, in Python floats."""
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def _inverse_eotf(v: float) -> float:
    return 12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055


@pytest.mark.parametrize("shape", [(), (12,), (3, 4), (2, 2, 3)])
def test_values_outside_the_range_follow_the_formulas_without_warnings(shape):
    """Every value, in arrays of any rank (0-d takes numpy's power, the others OpenCV's),
    float64 to 1e-12 and float32 to 1e-6; the branch not taken raises no warning (a
    negative base's power would be NaN with a RuntimeWarning)."""
    for v in VALUES:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            for f, ref in ((srgb_to_linear, _eotf), (linear_to_srgb, _inverse_eotf)):
                got64 = f(np.full(shape, v, np.float64))
                got32 = f(np.full(shape, v, np.float32))
                assert got64.shape == shape and got32.dtype == np.float32
                np.testing.assert_allclose(got64, ref(v), rtol=1e-12, atol=1e-15)
                np.testing.assert_allclose(got32, ref(v), rtol=1e-6, atol=1e-7)
    assert math.isclose(_eotf(0.5), 0.21404114048223255, rel_tol=1e-12)  # the reference


def test_a_negative_target_is_added_to_every_channel_not_a_flipped_scale():
    """Grey 0.2 to -0.1: a scale of -0.5 would reach it with its channels' signs flipped
    (0.1, 0.2, 0.3 -> -0.05, -0.1, -0.15); the scale stops at 0 and the rest is added alike:
    -0.1 in every channel. Grey 0.2 to 0.1 is a plain scale by 0.5."""
    image = np.array([[[0.1, 0.2, 0.3], [0.1, 0.2, 0.3]]], np.float32)
    grey = mean_grey(image).copy()
    target = np.array([[-0.1, 0.1]], np.float32)
    move_grey(image, grey, target, max_gain=4.0)
    np.testing.assert_allclose(image[0, 0], [-0.1, -0.1, -0.1], atol=1e-7)
    np.testing.assert_allclose(image[0, 1], [0.05, 0.1, 0.15], atol=1e-7)
    np.testing.assert_allclose(mean_grey(image), target, atol=1e-7)
