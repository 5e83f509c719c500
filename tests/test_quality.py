"""Quality measures: edge width against the analytic rise of a blurred step."""

import numpy as np
import pytest
from scipy import ndimage

from pipeline.core.quality import edge_points, edge_width, psnr
from pipeline.errors import InputError


def step_image(sigma, size=160, angle_deg=20.0):
    yy, xx = np.mgrid[:size, :size].astype(np.float64)
    a = np.radians(angle_deg)
    signed = (xx - size / 2) * np.cos(a) + (yy - size / 2) * np.sin(a)
    sharp = (signed > 0).astype(np.float64) * 0.6 + 0.2
    return ndimage.gaussian_filter(sharp, sigma).astype(np.float32)


@pytest.mark.parametrize("sigma", [1.5, 3.0, 5.0])
def test_gaussian_edge_width_is_2_563_sigma(sigma):
    image = step_image(sigma)
    points, normals = edge_points(image)
    # 10-90% of a Gaussian-blurred step: 2 * 1.2816 sigma (plus the pixel step's own width)
    expected = 2 * 1.2816 * np.sqrt(sigma**2 + 1 / 12)
    assert edge_width(image, points, normals) == pytest.approx(expected, abs=0.5)


def test_noise_and_ringing_do_not_make_edges_look_sharper():
    image = step_image(3.0)
    points, normals = edge_points(image)
    clean = edge_width(image, points, normals)
    noisy = image + np.random.default_rng(0).normal(0, 0.02, image.shape).astype(np.float32)
    yy, xx = np.mgrid[:160, :160]
    signed = (xx - 80) * np.cos(np.radians(20)) + (yy - 80) * np.sin(np.radians(20))
    ripple = 0.05 * np.sin(signed / 1.5) * (np.abs(signed) > 8)  # oscillation off the edge
    assert edge_width(noisy, points, normals) >= clean - 0.5
    assert edge_width(image + ripple.astype(np.float32), points, normals) >= clean - 0.5


def test_psnr_and_errors():
    a = np.zeros((4, 4))
    assert psnr(a + 0.1, a) == pytest.approx(20.0)
    with pytest.raises(InputError, match="shape"):
        psnr(np.zeros(3), np.zeros(4))
    with pytest.raises(InputError, match="edges"):
        edge_points(np.zeros((64, 64), np.float32))
