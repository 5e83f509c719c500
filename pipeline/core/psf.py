"""Lens PSFs and integrated PSFs of a moving detector (Eqs. 3-8).

Conventions: kernels are 2-D float64, odd-sized, centred, non-negative and sum
to 1; radii and blur diameters inside this module are in pixels (``*_px``).

Two independent ways to build an integrated PSF (IPSF, Eq. 5) are provided and
tested against each other:

* ``method="analytic"``: the closed-form IPSF of every linear piece of the
  motion (Eq. 6 for the pillbox, Eq. 7 for the Gaussian, generalised to any
  start/end blur), integrated over each pixel's area through its closed-form
  encircled energy ``E(rho)`` and a polar integral over the pixel.
* ``method="numeric"``: Eq. 5 by Gauss-Legendre quadrature over time of lens
  PSFs rasterised exactly (disk/square intersection areas for Eq. 3, products
  of erf differences for Eq. 4).

Notes
-----
Derivation of Eq. 6. With ``p(t) = p(0) + s t`` the blur diameter of Eq. 2 is
linear in t, ``|db/dt| = a s / v``, so on a piece where b runs monotonically
between ``b_lo`` and ``b_hi``::

    int P(r, b(t)) dt = v/(a s) int_{b_lo}^{b_hi} 4/(pi b^2) [b > 2r] db
                      = 4 v/(pi a s) (1/max(b_lo, 2r) - 1/b_hi)   (2r < b_hi)

A sweep through focus has two pieces with ``b_lo = 0``, giving::

    IP(r, u) = 2 v/(pi a s T) ((l0 + lT)/r - 2 l0/b(0) - 2 lT/b(T)),  v = uf/(u-f)

i.e. the printed Eq. 6 with an extra factor 2 (with it, IP integrates to 1 over
the plane; the printed form integrates to 1/2) and only valid when the sweep
crosses the point's focus. For the Gaussian of Eq. 4 (``c = g b``)::

    IP(r, u) = v/(sqrt(2 pi) r g a s T) (erfc(sqrt2 r/(g b(0))) + erfc(sqrt2 r/(g b(T))))

The printed Eq. 7 has ``erfc(r / (sqrt2 g b))``, which is the erfc of a
Gaussian of twice the width of Eq. 4, and drops the ``1/g``; we implement the
form derived from Eq. 4 (tests check both against quadrature of Eq. 5).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import special

from pipeline.core import optics, validate
from pipeline.core.lens import PSF_MODELS, Lens
from pipeline.core.motion import Profile
from pipeline.errors import InputError

MAX_KERNEL_SIZE = 4097
_GL_THETA = np.polynomial.legendre.leggauss(8)
_GL_TIME = np.polynomial.legendre.leggauss(6)


# ----------------------------------------------------------------------------- motion -> blur
def blur_pieces_px(
    lens: Lens, depth_mm: float, profile: Profile
) -> list[tuple[float, float, float]]:
    """Linear pieces ``(duration_s, b_start_px, b_end_px)`` of the blur diameter (Eq. 2).

    Segments of ``profile`` that cross the depth's focus ``v`` are split there,
    so ``b`` is linear (and the blur circle never changes side) on every piece.
    """
    v = optics.image_distance(lens.focal_length_mm, depth_mm)
    scale = lens.aperture_mm / v / lens.pixel_pitch_mm  # Eq. 2, in pixels
    pieces: list[tuple[float, float, float]] = []
    for duration, p0, p1 in profile.segments():
        d0, d1 = v - p0, v - p1
        if d0 * d1 < 0:  # crosses focus inside the segment
            frac = d0 / (d0 - d1)
            pieces.append((duration * frac, abs(d0) * scale, 0.0))
            pieces.append((duration * (1 - frac), 0.0, abs(d1) * scale))
        else:
            pieces.append((duration, abs(d0) * scale, abs(d1) * scale))
    return pieces


def _moving(b_lo: np.ndarray, b_hi: np.ndarray) -> np.ndarray:
    """Pieces whose blur changes enough for the per-piece closed forms to be well conditioned."""
    return (b_hi - b_lo) > 1e-9 * np.maximum(b_hi, 1.0)


def _piece_arrays(pieces):
    arr = np.asarray(pieces, dtype=np.float64).reshape(-1, 3)
    duration = arr[:, 0]
    b_lo = np.minimum(arr[:, 1], arr[:, 2])
    b_hi = np.maximum(arr[:, 1], arr[:, 2])
    return duration, b_lo, b_hi


# ----------------------------------------------------------------------------- radial forms
def ipsf_radial(r_px, pieces, *, model: str = "pillbox", gaussian_g: float = 1.0) -> np.ndarray:
    """IPSF value at radius ``r_px > 0`` (Eqs. 6, 7 generalised to any pieces), per px^2.

    Normalised by the exposure (a time average), so it integrates to 1 over the
    plane. Stationary pieces contribute the lens PSF itself (Eq. 3 / Eq. 4).
    """
    _check_model(model)
    r = np.asarray(r_px, dtype=np.float64)[..., None]
    duration, b_lo, b_hi = _piece_arrays(pieces)
    moving = _moving(b_lo, b_hi)
    delta_b = np.where(moving, b_hi - b_lo, 1.0)
    b_mid = 0.5 * (b_lo + b_hi)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if model == "pillbox":
            inner = 1.0 / np.maximum(np.maximum(b_lo, 2 * r), 1e-300) - 1.0 / b_hi
            moving_val = (4 / np.pi) * np.where(2 * r < b_hi, inner, 0.0)  # Eq. 6 (corrected)
            still_val = np.where(2 * r < b_mid, 4 / (np.pi * b_mid**2), 0.0)  # Eq. 3
        else:
            g = gaussian_g
            moving_val = (
                special.erfc(np.sqrt(2) * r / (g * b_hi))
                - special.erfc(np.sqrt(2) * r / (g * np.maximum(b_lo, 1e-300)))
            ) / (np.sqrt(2 * np.pi) * r * g)  # Eq. 7 (corrected)
            c = g * b_mid
            still_val = 2 / (np.pi * c**2) * np.exp(-2 * r**2 / c**2)  # Eq. 4
    value = np.where(moving, duration / delta_b * moving_val, duration * still_val)
    return np.nan_to_num(value.sum(axis=-1)) / duration.sum()


def encircled_energy(rho_px, pieces, *, model: str = "pillbox", gaussian_g: float = 1.0):
    """Fraction of the IPSF's energy within radius ``rho_px`` (closed form of Eqs. 6, 7).

    ``E(rho) = (1/T) sum_pieces (d / db) int_{b_lo}^{b_hi} e_b(rho) db`` with the lens
    PSF's own encircled energy ``e_b = min(1, 4 rho^2 / b^2)`` (Eq. 3) or
    ``1 - exp(-2 rho^2 / (g b)^2)`` (Eq. 4).
    """
    _check_model(model)
    rho = np.asarray(rho_px, dtype=np.float64)[..., None]
    duration, b_lo, b_hi = _piece_arrays(pieces)
    moving = _moving(b_lo, b_hi)
    delta_b = np.where(moving, b_hi - b_lo, 1.0)
    b_mid = np.maximum(0.5 * (b_lo + b_hi), 1e-300)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if model == "pillbox":
            two_rho = 2 * rho
            linear = np.clip(np.minimum(b_hi, two_rho) - b_lo, 0.0, None)
            tail = np.where(
                two_rho < b_hi,
                4 * rho**2 * (1 / np.maximum(np.maximum(b_lo, two_rho), 1e-300) - 1 / b_hi),
                0.0,
            )
            moving_val = (linear + tail) / delta_b
            still_val = np.minimum(1.0, 4 * rho**2 / b_mid**2)
        else:
            k = 2 * rho**2 / gaussian_g**2

            def antiderivative(b):
                # int exp(-k/b^2) db = b exp(-k/b^2) + sqrt(pi k) erf(sqrt(k)/b)
                safe_b = np.maximum(b, 1e-300)
                return safe_b * np.exp(-k / safe_b**2) + np.sqrt(np.pi * k) * special.erf(
                    np.sqrt(k) / safe_b
                )

            moving_val = 1.0 - (antiderivative(b_hi) - antiderivative(b_lo)) / delta_b
            still_val = 1.0 - np.exp(-k / b_mid**2)
    value = np.where(moving, moving_val, still_val)
    return np.nan_to_num(value) @ duration / duration.sum()


# ----------------------------------------------------------------------------- rasterising
def _pixel_integrate_radial(energy, half: int, theta_order: int = 8) -> np.ndarray:
    """Integrate a radially symmetric density over every pixel of a ``2 half + 1`` grid.

    ``energy(rho)`` is the density's encircled energy (fraction within ``rho``); a
    pixel's share is ``(1/2 pi) int (E(rho_out(t)) - E(rho_in(t))) dt`` over the
    angles ``t`` the pixel subtends, split at its corners and integrated by
    Gauss-Legendre (``theta_order`` nodes per piece). Computed on one octant and mirrored.
    """
    nodes, weights = _GL_THETA if theta_order == 8 else np.polynomial.legendre.leggauss(theta_order)
    ys, xs = np.nonzero(np.triu(np.ones((half + 1, half + 1), dtype=bool)))  # y <= x
    xs_f, ys_f = xs.astype(np.float64), ys.astype(np.float64)
    octant = np.zeros(xs.size)
    centre = (xs == 0) & (ys == 0)
    # The centre pixel contains the origin: rho(t) = 0.5 / cos(t) on t in [0, pi/4], times 8.
    t = (nodes + 1) * (np.pi / 8)
    octant[centre] = 8 * (np.pi / 8) * np.dot(weights, energy(0.5 / np.cos(t))) / (2 * np.pi)
    others = ~centre
    x, y = xs_f[others], ys_f[others]
    corner_angles = np.sort(
        np.stack([np.arctan2(y + dy, x + dx) for dx in (-0.5, 0.5) for dy in (-0.5, 0.5)], axis=-1),
        axis=-1,
    )
    total = np.zeros(x.size)
    for k in range(3):
        lo, hi = corner_angles[:, k], corner_angles[:, k + 1]
        half_width = 0.5 * (hi - lo)
        theta = 0.5 * (hi + lo)[:, None] + half_width[:, None] * nodes[None, :]
        cos_t, sin_t = np.cos(theta), np.sin(theta)
        tx_lo, tx_hi = _slab(x[:, None], cos_t)
        ty_lo, ty_hi = _slab(y[:, None], sin_t)
        rho_in = np.maximum(np.maximum(tx_lo, ty_lo), 0.0)
        rho_out = np.maximum(np.minimum(tx_hi, ty_hi), rho_in)
        diff = energy(rho_out) - energy(rho_in)
        total += half_width * (diff @ weights)
    octant[others] = total / (2 * np.pi)
    quadrant = np.zeros((half + 1, half + 1))
    quadrant[ys, xs] = octant
    quadrant[xs, ys] = octant
    return _mirror_quadrant(quadrant)


def _slab(centre: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters where a ray from the origin enters/leaves ``|coord - centre| <= 0.5``."""
    parallel = np.abs(direction) < 1e-15
    safe = np.where(parallel, 1.0, direction)
    t_a, t_b = (centre - 0.5) / safe, (centre + 0.5) / safe
    inside = np.abs(centre) <= 0.5
    lo = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t_a, t_b))
    hi = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t_a, t_b))
    return lo, hi


def _mirror_quadrant(quadrant: np.ndarray) -> np.ndarray:
    top = np.concatenate([quadrant[:, :0:-1], quadrant], axis=1)
    return np.concatenate([top[:0:-1], top], axis=0)


def _disk_quadrant_area(x: np.ndarray, y: np.ndarray, radius: float) -> np.ndarray:
    """Area of the disk of ``radius`` (centred at 0) inside ``[0, x] x [0, y]``, x, y >= 0
    (arrays broadcast: a row of ``x`` and a column of ``y`` give the grid, with the terms
    of ``x`` alone computed once per column)."""
    x = np.minimum(x, radius)
    y = np.minimum(y, radius)

    def segment(u):  # int_0^u sqrt(R^2 - s^2) ds
        u = np.clip(u, 0.0, radius)
        return 0.5 * (
            u * np.sqrt(np.maximum(radius**2 - u**2, 0.0))
            + radius**2 * np.arcsin(np.minimum(u / radius, 1.0))
        )

    x_switch = np.minimum(x, np.sqrt(np.maximum(radius**2 - y**2, 0.0)))
    return y * x_switch + segment(x) - segment(x_switch)


def raster_pillbox(diameter_px: float, half: int) -> np.ndarray:
    """Eq. 3 integrated exactly over each pixel (disk/square intersection areas)."""
    if diameter_px <= 1e-12:
        return _delta(half)
    radius = 0.5 * diameter_px
    # Pixel edges past the disk clamp to the radius, so their cumulative areas are equal
    # and the pixels there exactly 0: the disk is rasterised out to its reach only and
    # zero-padded (the same values; a ninth of the work for a disk of half the kernel's
    # width, as most of a focal stack's are).
    reach = raster_reach("pillbox", diameter_px, half)
    edges = np.arange(reach + 2) - 0.5
    edges[0] = 0.0
    cumulative = _disk_quadrant_area(edges[None, :], edges[:, None], radius)
    quadrant = np.diff(np.diff(cumulative, axis=0), axis=1)
    quadrant[0, :] *= 2  # the centre row/column straddle the axes: their halves mirror
    quadrant[:, 0] *= 2
    kernel = np.clip(_mirror_quadrant(quadrant), 0.0, None)  # rounding leaves -1e-17s
    kernel /= np.pi * radius**2
    return kernel if reach == half else np.pad(kernel, half - reach)


def raster_reach(model: str, diameter_px: float, half: int) -> int:
    """The half-size beyond which a ``2 half + 1`` raster of Eq. 3 or 4 is exactly 0.

    ``raster_lens_psf(model, d, half)`` is ``raster_lens_psf(model, d, reach)``
    zero-padded to ``half``, so a sum of many rasters (:func:`pipeline.core.stack_kernel.
    focal_stack_psf`) can add each over its reach only. A pillbox reaches the pixels its
    disk touches (at most ``ceil(d / 2 + 0.5)``, :func:`kernel_size`); a Gaussian has no
    edge.
    """
    if model == "pillbox":
        return min(half, math.ceil(0.5 * diameter_px + 0.5))
    return half


def raster_gaussian(diameter_px: float, half: int, *, gaussian_g: float = 1.0) -> np.ndarray:
    """Eq. 4 integrated exactly over each pixel (separable: products of erf differences)."""
    c = gaussian_g * diameter_px
    if c <= 1e-12:
        return _delta(half)
    sigma = 0.5 * c  # exp(-2 r^2 / c^2) = exp(-r^2 / (2 sigma^2))
    edges = (np.arange(-half, half + 2) - 0.5) / (sigma * np.sqrt(2))
    profile = 0.5 * np.diff(special.erf(edges))
    return np.outer(profile, profile)


def _delta(half: int) -> np.ndarray:
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    kernel[half, half] = 1.0
    return kernel


# ----------------------------------------------------------------------------- sizes
def kernel_size(max_blur_px: float, *, model: str = "pillbox", gaussian_g: float = 1.0) -> int:
    """Odd kernel size that holds a blur of diameter ``max_blur_px``.

    Pillbox: the whole disk (radius b/2) plus the pixels it touches. Gaussian:
    radius ``2 g b`` (4 sigma; the truncated tail holds ``exp(-8) = 3e-4`` of the energy).
    """
    _check_model(model)
    if not math.isfinite(max_blur_px) or max_blur_px < 0:
        raise InputError(f"max_blur_px must be finite and >= 0, got {max_blur_px!r}")
    radius = 0.5 * max_blur_px if model == "pillbox" else 2.0 * gaussian_g * max_blur_px
    return 2 * math.ceil(radius + 0.5) + 1


def _resolve_size(size: int | None, max_blur_px: float, model: str, g: float) -> int:
    if size is None:
        size = kernel_size(max_blur_px, model=model, gaussian_g=g)
        if size > MAX_KERNEL_SIZE:
            raise InputError(
                f"the blur reaches {max_blur_px:.0f} px, which needs a {size} px kernel "
                f"(> {MAX_KERNEL_SIZE}); pass a smaller size (--size) to truncate it"
            )
        return size
    if (
        isinstance(size, bool)
        or not isinstance(size, (int, np.integer))
        or size < 1
        or size % 2 == 0
    ):
        raise InputError(f"size must be a positive odd integer, got {size!r}")
    if size > MAX_KERNEL_SIZE:  # a 4097 px kernel already spans a 12-Mpx frame's width
        raise InputError(f"size must be at most {MAX_KERNEL_SIZE} px, got {size}")
    return int(size)


def _check_model(model: str) -> None:
    if model not in PSF_MODELS:
        raise InputError(f"model must be one of {', '.join(PSF_MODELS)}, got {model!r}")


def _check_depth(depth_mm: float) -> None:
    if not isinstance(depth_mm, (int, float, np.floating)) or math.isnan(depth_mm):
        raise InputError(f"depth_mm must be a number (mm, inf allowed), got {depth_mm!r}")


def _normalise(kernel: np.ndarray) -> np.ndarray:
    kernel = np.clip(kernel, 0.0, None)
    total = kernel.sum()
    if not np.isfinite(total) or total <= 0:
        raise InputError("the PSF has no energy inside the kernel; pass a larger size=")
    return kernel / total


# ----------------------------------------------------------------------------- public kernels
def lens_psf(
    lens: Lens,
    depth_mm: float,
    image_distance_mm: float,
    *,
    model: str | None = None,
    size: int | None = None,
) -> np.ndarray:
    """Pixel kernel of a static camera: Eq. 3 or Eq. 4 with ``b`` from Eq. 2.

    Parameters
    ----------
    lens : Lens
    depth_mm : float
        Scene depth ``u`` (mm, ``math.inf`` allowed, must exceed f).
    image_distance_mm : float
        Detector position ``p``.
    model : {"pillbox", "gaussian"}, optional
        Default: the lens profile's.
    size : int, optional
        Odd kernel size; default from the blur (:func:`kernel_size`).
    """
    model = model or lens.psf_model
    _check_model(model)
    _check_depth(depth_mm)
    v = optics.image_distance(lens.focal_length_mm, depth_mm)
    b_px = lens.blur_px(v, image_distance_mm)
    half = _resolve_size(size, b_px, model, lens.gaussian_g) // 2
    if model == "pillbox":
        return _normalise(raster_pillbox(b_px, half))
    return _normalise(raster_gaussian(b_px, half, gaussian_g=lens.gaussian_g))


def integrated_psf(
    lens: Lens,
    depth_mm: float,
    profile: Profile,
    *,
    model: str | None = None,
    size: int | None = None,
    method: str = "auto",
    theta_order: int = 8,
    time_order: int = 6,
    time_step_px: float = 0.5,
) -> np.ndarray:
    """Pixel kernel of the integrated PSF of a moving detector (Eq. 5).

    Parameters
    ----------
    lens : Lens
    depth_mm : float
        Scene depth ``u`` (mm; ``math.inf`` allowed; must exceed the focal length).
    profile : pipeline.core.motion.Profile
        Detector motion p(t); any piecewise-linear motion (pauses, reversals).
    model : {"pillbox", "gaussian"}, optional
        Lens PSF (Eq. 3 or 4); default the lens profile's.
    size : int, optional
        Odd kernel size; default from the largest blur during the motion.
    method : {"auto", "analytic", "numeric"}
        "analytic": closed-form Eqs. 6/7 (corrected, see module notes) integrated
        over pixel areas, except on pieces whose blur changes by less than
        ``SMALL_CHANGE_PX`` (see :func:`_analytic_ipsf`); "numeric": quadrature of
        Eq. 5 over time. "auto" is "analytic". Neither is exact: both agree with a
        fine quadrature of Eq. 5 to ~1e-4 (L1) or better.
    theta_order : int
        "analytic": Gauss-Legendre nodes per angular piece of a pixel's polar integral.
    time_order, time_step_px : int, float
        "numeric": Gauss-Legendre nodes per time sub-interval, each sub-interval
        spanning at most ``time_step_px`` px of blur diameter.
        (Accuracy/time trade-offs: ``flexdof bench accuracy``.)

    Returns
    -------
    ndarray
        2-D float64, odd size, centred, non-negative, sums to 1.

    Notes
    -----
    ``IP(r, u) = (1/T) int_0^T P(r, u, p(t)) dt`` (Eq. 5, normalised by T).
    For a rolling-shutter row, pass ``profile.window(t_row, t_row + exposure)``.

    Examples
    --------
    The paper's Sec. 4.1 sweep (12.5 mm f/1.4, 450 mm to 2 m in 0.36 s): the IPSF of
    a point at 750 mm is an odd-sized, centred kernel that sums to 1.

    >>> from pipeline.core import optics
    >>> from pipeline.core.lens import Lens
    >>> from pipeline.core.motion import constant_speed
    >>> lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=4.65,
    ...             width_px=1024, height_px=768)
    >>> far, near = optics.image_distance(12.5, 2000.0), optics.image_distance(12.5, 450.0)
    >>> kernel = integrated_psf(lens, 750.0, constant_speed(far, (near - far) / 0.36, 0.36))
    >>> centred = bool(kernel.argmax() == kernel.size // 2)
    >>> kernel.shape[0] % 2, round(float(kernel.sum()), 6), centred
    (1, 1.0, True)
    """
    model = model or lens.psf_model
    _check_model(model)
    _check_depth(depth_mm)
    if not isinstance(profile, Profile):
        raise InputError(
            f"profile must be a pipeline.core.motion.Profile, got {type(profile).__name__}"
        )
    if method not in ("auto", "analytic", "numeric"):
        raise InputError(f"method must be 'auto', 'analytic' or 'numeric', got {method!r}")
    validate.whole("theta_order", theta_order)
    validate.whole("time_order", time_order)
    validate.positive("time_step_px", time_step_px)
    pieces = blur_pieces_px(lens, depth_mm, profile)
    max_blur = max(max(b0, b1) for _, b0, b1 in pieces)
    half = _resolve_size(size, max_blur, model, lens.gaussian_g) // 2
    g = lens.gaussian_g
    if method == "numeric":
        return _normalise(_numeric_ipsf(pieces, half, model, g, time_order, time_step_px))
    return _normalise(_analytic_ipsf(pieces, half, model, g, theta_order))


def raster_lens_psf(model: str, diameter_px: float, half: int, g: float = 1.0) -> np.ndarray:
    """Eq. 3 or Eq. 4 of diameter ``diameter_px`` integrated over a ``2 half + 1`` pixel grid."""
    if model == "pillbox":
        return raster_pillbox(diameter_px, half)
    return raster_gaussian(diameter_px, half, gaussian_g=g)


# Blur change (px of diameter) below which a piece of the motion is rasterised as the
# Gauss-Legendre average of exact lens PSFs instead of through the closed form.
SMALL_CHANGE_PX = 0.5


def _analytic_ipsf(pieces, half: int, model: str, g: float, theta_order: int = 8) -> np.ndarray:
    """Eqs. 6/7 integrated over pixels; pieces with a small blur change by exact rasters.

    Why a threshold. The closed form is exact in ``r``, but its pixel integral is a
    Gauss-Legendre polar quadrature of the encircled energy ``E(rho)``. For the pillbox
    a piece from ``b_lo`` to ``b_hi`` gives ``E`` a bend of width ``(b_hi - b_lo) / 2``
    in ``rho`` around the disk edge: as the blur change goes to 0 it becomes the kink
    of the still pillbox, which the polar rule (``theta_order`` nodes per pixel
    piece, ~1/8 px apart) cannot resolve: L1 error ~2e-3 (b = 2.25 px), ~1.6e-4
    (b = 7 px) however small the change. The alternative for such a piece is the
    time average of exactly rasterised lens PSFs (the disk/square areas of Eq. 3, the
    erf products of Eq. 4) by 6-node Gauss-Legendre over ``b``; its error is that
    of the rule on the smooth-between-corner-crossings ``K(b)``, which grows with the
    change: measured against a 0.02 px quadrature of Eq. 5 it is below 1e-14 at
    0.2 px and 1e-5 at 0.5 px (b = 2.25, 7, 20 px), while the closed form is at
    2e-5-5e-5 at 0.5 px and better than the rule from ~1 px on. Hence
    ``SMALL_CHANGE_PX = 0.5``, the same 0.5 px step the numeric method uses, so on
    these pieces both methods compute the same sum. The Gaussian's ``E`` is smooth
    (its closed form is accurate at any change; its ``1/delta_b`` cancellation is
    also avoided below the threshold).
    """
    duration, b_lo, b_hi = _piece_arrays(pieces)
    total = duration.sum()
    closed = (b_hi - b_lo) >= SMALL_CHANGE_PX
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    if closed.any():
        closed_pieces = [pieces[i] for i in np.flatnonzero(closed)]
        share = duration[closed].sum() / total
        kernel += share * _pixel_integrate_radial(
            lambda rho: encircled_energy(rho, closed_pieces, model=model, gaussian_g=g),
            half,
            theta_order,
        )
    nodes, weights = _GL_TIME
    for i in np.flatnonzero(~closed):  # small changes and pauses: exact lens PSFs
        if b_hi[i] == b_lo[i]:
            kernel += duration[i] / total * raster_lens_psf(model, b_lo[i], half, g)
            continue
        for node, weight in zip(nodes, weights):
            b = b_lo[i] + (b_hi[i] - b_lo[i]) * 0.5 * (node + 1)
            kernel += duration[i] / total * 0.5 * weight * raster_lens_psf(model, b, half, g)
    return kernel


def _numeric_ipsf(
    pieces, half: int, model: str, g: float, order: int = 6, step_px: float = 0.5
) -> np.ndarray:
    """Eq. 5 by composite Gauss-Legendre over time, sub-intervals spanning <= step_px of blur."""
    nodes, weights = _GL_TIME if order == 6 else np.polynomial.legendre.leggauss(order)
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    total = sum(d for d, _, _ in pieces)
    for duration, b0, b1 in pieces:
        n_sub = max(1, math.ceil(abs(b1 - b0) / step_px))
        edges = np.linspace(0.0, 1.0, n_sub + 1)
        for lo, hi in itertools.pairwise(edges):
            for node, weight in zip(nodes, weights):
                frac = lo + (hi - lo) * 0.5 * (node + 1)
                b = b0 + (b1 - b0) * frac
                kernel += (
                    (duration / total)
                    * (hi - lo)
                    * 0.5
                    * weight
                    * raster_lens_psf(model, b, half, g)
                )
    return kernel
