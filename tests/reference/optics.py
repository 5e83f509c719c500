"""Thin-lens geometry, written from scratch (no ``pipeline`` import).

Conventions of the simulator under test (``pipeline.scene``): the scene's radiance, alpha
and depth maps sit on the sensor's pixel grid *as imaged at the reference detector
position* ``p_ref``; the optical axis passes through the grid centre
``((rows - 1) / 2, (cols - 1) / 2)``; at detector position ``p`` the image is the grid
image scaled by ``m = p / p_ref`` about that centre.

Derivation used by both renderers (all lengths mm, ``D = 1/u`` the inverse depth):

* Lens law ``1/f = 1/u + 1/v``; the detector at ``p`` is focused at ``D_p = 1/f - 1/p``.
* A ray from sensor point ``s`` (mm from the axis) through aperture point ``A``
  (``|A| <= a/2``, ``a = f/N``) heads for the conjugate of ``s``: depth ``u_p`` (``1/u_p =
  D_p``), lateral ``-s u_p / p``. It meets the plane at depth ``u`` at lateral
  ``X = A (1 - u/u_p) - s u / p``. A point at lateral ``X``, depth ``u`` sits on the grid
  (p_ref) at ``g = -X p_ref / (u * pitch)`` px, so the ray lands on the grid at
  ``g = s p_ref / (p pitch) - A (p_ref / pitch) (D - D_p)``:
  centre ``x / m`` (``x = s / pitch``) and, over the aperture, a disk of *signed* radius
  ``rho = (a/2) (p_ref / pitch) (D - D_p)`` grid px.
* Check against Eq. 2: ``D - D_p = 1/p - 1/v = (v - p) / (p v)`` so
  ``2 |rho| = a |v - p| / v / pitch * (p_ref / p) = b_px / m``: Eq. 2's blur diameter on
  the detector, expressed in grid px (tests/test_simulate_reference.py checks this).
"""

from __future__ import annotations

import math

import numpy as np


def image_distance(f_mm: float, u_mm: float) -> float:
    """``v`` with ``1/f = 1/u + 1/v``; ``u = inf`` gives ``f``."""
    return f_mm if math.isinf(u_mm) else f_mm * u_mm / (u_mm - f_mm)


def focused_inverse_depth(f_mm: float, p_mm) -> np.ndarray:
    """``D_p = 1/f - 1/p`` (1/mm): the inverse depth in focus at detector position ``p``."""
    return 1.0 / f_mm - 1.0 / np.asarray(p_mm, dtype=np.float64)


def grid_radius(f_mm, f_number, pitch_mm, p_ref_mm, inv_depth, p_mm) -> np.ndarray:
    """Signed radius (grid px at p_ref) of the disk a pixel's aperture rays cover at depth 1/D."""
    a = f_mm / f_number
    return 0.5 * a * (p_ref_mm / pitch_mm) * (
        np.asarray(inv_depth, dtype=np.float64) - focused_inverse_depth(f_mm, p_mm)
    )


def blur_diameter_px(f_mm, f_number, pitch_mm, u_mm, p_mm) -> float:
    """Eq. 2 on the detector, in detector pixels: ``a |v - p| / v / pitch``."""
    v = image_distance(f_mm, u_mm)
    return (f_mm / f_number) * abs(v - p_mm) / v / pitch_mm
