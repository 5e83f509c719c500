"""Scenes and cameras for the forward model (Sec. 3-7).

A :class:`Scene` is one or more *surfaces*: linear radiance ``(rows, cols[, channels])``,
coverage ``alpha`` and depth (mm) per pixel, all on the sensor's pixel grid as imaged at
the reference detector position ``p_ref`` (the grid is centred on the optical axis). A
depth map is one surface; planar layers are one surface each with a constant depth; a
tilted or curved surface is a depth map.

Depth conventions: ``math.inf`` is a valid depth (infinitely far). Pixels
*without* depth are NaN, ``-inf`` or ``<= 0``; the caller chooses what to do with them
(``missing_depth="fill"``: nearest valid depth; ``"exclude"``: zero radiance and zero
alpha), there is no default. Real depth maps that mark unknown pixels with ``+inf`` must
convert those to NaN first (``stacks/generate_motorcycle.py`` does).

A :class:`Camera` is a :class:`~pipeline.core.lens.Lens`, a detector motion p(t)
(:class:`~pipeline.core.motion.Profile`, Eq. 5), a shutter (global, or rolling with the lens's
line time, Sec. 6) and an optional :class:`Exposure` (photon level and read noise).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from pipeline.core import validate
from pipeline.core.lens import PSF_MODELS, SHUTTERS, Lens
from pipeline.core.motion import Profile
from pipeline.errors import InputError

MISSING_DEPTH_CHOICES = ("fill", "exclude")


@dataclasses.dataclass(frozen=True, eq=False)
class Surface:
    """One surface: radiance ``(rows, cols, channels)`` float32, alpha and depth ``(rows, cols)``.

    Build surfaces through :class:`Scene`; the arrays are validated there.
    """

    radiance: np.ndarray
    alpha: np.ndarray
    depth_mm: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """A scene: surfaces on one pixel grid, plus what was done with missing depth.

    Use :meth:`from_depth` (a depth map) or :meth:`from_planes` (planar layers).
    """

    surfaces: tuple[Surface, ...]
    channels_axis: bool
    missing_pixels: int = 0
    missing_depth: str | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.surfaces[0].alpha.shape

    @property
    def dtype(self) -> np.dtype:
        return self.surfaces[0].radiance.dtype

    @classmethod
    def from_depth(
        cls,
        radiance: np.ndarray,
        depth_mm: np.ndarray,
        *,
        alpha: np.ndarray | None = None,
        missing_depth: str | None = None,
    ) -> Scene:
        """A scene from radiance and a depth map (fronto-parallel, tilted or curved).

        Parameters
        ----------
        radiance : ndarray
            Linear radiance, ``(rows, cols)`` or ``(rows, cols, channels)``, finite.
            float32 stays float32, anything else becomes float64.
        depth_mm : ndarray
            Depth ``u`` (mm) per pixel, ``(rows, cols)``; ``inf`` is infinitely far;
            NaN, ``-inf`` and values ``<= 0`` are missing.
        alpha : ndarray, optional
            Coverage in [0, 1] (default 1 everywhere).
        missing_depth : {"fill", "exclude"}, optional
            Required when any depth is missing: ``"fill"`` gives a missing pixel the depth
            of the nearest valid pixel; ``"exclude"`` sets its radiance and alpha to 0.
        """
        rad, chan = _check_radiance(radiance, "radiance")
        depth = _check_depth_shape(depth_mm, rad.shape[:2], "depth_mm")
        a = _check_alpha(alpha, rad.shape[:2], rad.dtype, "alpha")
        depth, rad, a, missing = _handle_missing(depth, rad, a, missing_depth, "depth_mm")
        return cls(
            (Surface(rad, a, depth),),
            chan,
            missing_pixels=missing,
            missing_depth=missing_depth if missing else None,
        )

    @classmethod
    def from_planes(cls, planes) -> Scene:
        """A scene of fronto-parallel planar layers.

        Parameters
        ----------
        planes : sequence of (radiance, alpha, depth_mm)
            Each plane's radiance ``(rows, cols[, channels])``, coverage (or None for 1)
            and one depth in mm (``inf`` allowed). All planes share one grid.
        """
        planes = list(planes)
        if not planes:
            raise InputError("planes must hold at least one (radiance, alpha, depth_mm) tuple")
        surfaces, chans = [], set()
        shape = None
        for i, plane in enumerate(planes):
            if len(plane) != 3:
                raise InputError(f"planes[{i}] must be (radiance, alpha, depth_mm), got {plane!r}")
            radiance, alpha, depth = plane
            rad, chan = _check_radiance(radiance, f"planes[{i}] radiance")
            if shape is not None and rad.shape != shape:
                raise InputError(
                    f"planes[{i}] radiance has shape {rad.shape}, the first plane {shape}"
                )
            shape = rad.shape
            chans.add(chan)
            if not isinstance(depth, (int, float, np.floating)) or not depth > 0:
                raise InputError(f"planes[{i}] depth_mm must be a number > 0, got {depth!r}")
            a = _check_alpha(alpha, rad.shape[:2], rad.dtype, f"planes[{i}] alpha")
            surfaces.append(Surface(rad, a, np.full(rad.shape[:2], float(depth))))
        dtypes = {s.radiance.dtype for s in surfaces}
        if len(dtypes) > 1:
            surfaces = [
                dataclasses.replace(s, radiance=s.radiance.astype(np.float64)) for s in surfaces
            ]
        return cls(tuple(surfaces), chans.pop() if len(chans) == 1 else True)


def _check_radiance(radiance, name: str) -> tuple[np.ndarray, bool]:
    arr = np.asarray(radiance)
    if arr.dtype.kind not in "fiu" or arr.ndim not in (2, 3) or 0 in arr.shape:
        raise InputError(
            f"{name} must be a real (rows, cols[, channels]) array, got shape {arr.shape} "
            f"dtype {arr.dtype}"
        )
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has NaN/Inf values; radiance must be finite")
    dtype = np.float32 if arr.dtype == np.float32 else np.float64
    chan = arr.ndim == 3
    arr = arr.astype(dtype, copy=False)
    return (arr if chan else arr[:, :, None]), chan


def _check_depth_shape(depth_mm, shape, name: str) -> np.ndarray:
    depth = np.asarray(depth_mm)
    if depth.dtype.kind not in "fiu" or depth.shape != tuple(shape):
        raise InputError(
            f"{name} must be a real array of shape {tuple(shape)} (the radiance's rows, cols), "
            f"got shape {depth.shape} dtype {depth.dtype}"
        )
    return depth.astype(np.float64)


def _check_alpha(alpha, shape, dtype, name: str) -> np.ndarray:
    if alpha is None:
        return np.ones(shape, dtype=dtype)
    a = np.asarray(alpha)
    if a.shape != tuple(shape) or a.dtype.kind not in "fiub":
        raise InputError(f"{name} must be a real array of shape {tuple(shape)}, got {a.shape}")
    a = a.astype(dtype)
    if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
        raise InputError(f"{name} must be in [0, 1] and finite")
    return a


def _handle_missing(depth, rad, alpha, missing_depth, name):
    missing = np.isnan(depth) | (depth <= 0)  # -inf is <= 0
    count = int(np.count_nonzero(missing))
    if count == 0:
        return depth, rad, alpha, 0
    if missing_depth not in MISSING_DEPTH_CHOICES:
        raise InputError(
            f"{name} has {count} pixels without depth (NaN, -inf or <= 0); pass "
            f"missing_depth='fill' (nearest valid depth) or 'exclude' (zero radiance and "
            f"alpha there), got missing_depth={missing_depth!r}"
        )
    if count == depth.size:
        raise InputError(f"{name} has no valid depth at all ({count} pixels missing)")
    depth = depth.copy()
    if missing_depth == "fill":
        _, (ri, ci) = ndimage.distance_transform_edt(missing, return_indices=True)
        depth[missing] = depth[ri[missing], ci[missing]]
    else:
        rad = np.where(missing[:, :, None], 0, rad).astype(rad.dtype)
        alpha = np.where(missing, 0, alpha).astype(alpha.dtype)
        depth[missing] = np.nanmax(np.where(missing, np.nan, depth))  # any valid depth; alpha 0
    return depth, rad, alpha, count


def mean_position(profile: Profile) -> float:
    """Time average of p(t) over the profile (exact for piecewise-linear motion)."""
    t, p = profile.times_s, profile.image_distances_mm
    return float(np.sum(np.diff(t) * 0.5 * (p[1:] + p[:-1])) / profile.exposure_s)


@dataclasses.dataclass(frozen=True)
class Exposure:
    """Photon level of a capture: shot noise (Poisson) plus read noise (Gaussian).

    Parameters
    ----------
    electrons_at_unit : float
        Electrons a pixel collects over its exposure at radiance 1.0 (> 0).
    read_noise_e : float
        Read noise standard deviation in electrons (>= 0).
    """

    electrons_at_unit: float
    read_noise_e: float = 0.0

    def __post_init__(self) -> None:
        e, r = self.electrons_at_unit, self.read_noise_e
        validate.positive("electrons_at_unit", e)
        validate.non_negative("read_noise_e", r)


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """Lens + shutter + detector motion p(t) + exposure.

    Parameters
    ----------
    lens : Lens
    motion : Profile
        Detector position p(t) over the whole capture (for a rolling shutter: from the
        first row's start to the last row's end).
    shutter : {"global", "rolling"}, optional
        Default: the lens profile's. Rolling: row ``r`` integrates
        ``[t0 + r line_time, t0 + r line_time + row_exposure_s]`` (Sec. 6).
    row_exposure_s : float, optional
        Rolling shutter only: each row's exposure; default the motion's duration minus
        ``(rows - 1) * line_time``.
    exposure : Exposure, optional
        Photon level and read noise; None renders noise-free.
    psf_model : {"pillbox", "gaussian"}, optional
        Override the lens profile's PSF model (Eq. 3 or 4).
    reference_image_distance_mm : float, optional
        ``p_ref``, the detector position at which the scene grid is defined; the image
        scales by ``p(t) / p_ref`` about the centre. Default: the time average of p(t).
    """

    lens: Lens
    motion: Profile
    shutter: str | None = None
    row_exposure_s: float | None = None
    exposure: Exposure | None = None
    psf_model: str | None = None
    reference_image_distance_mm: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.lens, Lens):
            raise InputError(
                f"lens must be a pipeline.core.lens.Lens, got {type(self.lens).__name__}"
            )
        if not isinstance(self.motion, Profile):
            raise InputError(
                f"motion must be a pipeline.core.motion.Profile, got {type(self.motion).__name__}"
            )
        if self.shutter is not None and self.shutter not in SHUTTERS:
            raise InputError(f"shutter must be one of {', '.join(SHUTTERS)}, got {self.shutter!r}")
        if self.psf_model is not None and self.psf_model not in PSF_MODELS:
            raise InputError(
                f"psf_model must be one of {', '.join(PSF_MODELS)}, got {self.psf_model!r}"
            )
        if self.effective_shutter == "rolling" and self.lens.line_time_us <= 0:
            raise InputError(
                f"a rolling shutter needs the lens's line_time_us > 0 ({self.lens.name})"
            )
        if self.row_exposure_s is not None:
            validate.positive("row_exposure_s", self.row_exposure_s)
        if self.exposure is not None and not isinstance(self.exposure, Exposure):
            raise InputError(f"exposure must be an Exposure, got {type(self.exposure).__name__}")
        ref = self.reference_image_distance_mm
        if ref is not None:
            validate.positive("reference_image_distance_mm", ref)

    @classmethod
    def static(cls, lens: Lens, image_distance_mm: float, exposure_s: float, **options) -> Camera:
        """A normal capture: the detector rests at ``image_distance_mm`` for ``exposure_s``."""
        validate.positive("exposure_s", exposure_s)
        return cls(lens, Profile([0.0, exposure_s], [image_distance_mm] * 2), **options)

    @property
    def effective_shutter(self) -> str:
        return self.shutter or self.lens.shutter

    @property
    def model(self) -> str:
        return self.psf_model or self.lens.psf_model

    @property
    def line_time_s(self) -> float:
        return self.lens.line_time_us * 1e-6

    @property
    def reference_mm(self) -> float:
        """``p_ref``: given, else the time average of p(t) (trapezoid over the knots)."""
        if self.reference_image_distance_mm is not None:
            return float(self.reference_image_distance_mm)
        return mean_position(self.motion)

    def row_windows(self, rows: int) -> list[tuple[float, float]]:
        """Exposure window ``(start_s, end_s)`` of every row (the same for a global shutter)."""
        t0, t1 = float(self.motion.times_s[0]), float(self.motion.times_s[-1])
        if self.effective_shutter == "global":
            return [(t0, t1)] * rows
        readout = (rows - 1) * self.line_time_s
        exposure = self.row_exposure_s
        if exposure is None:
            exposure = (t1 - t0) - readout
        if exposure <= 0 or t0 + readout + exposure > t1 + 1e-12:
            raise InputError(
                f"rolling shutter: {rows} rows need {readout:.6g} s of readout plus a row "
                f"exposure > 0 within the motion's {t1 - t0:.6g} s; lengthen the motion "
                f"(row_exposure_s={self.row_exposure_s!r})"
            )
        return [
            (t0 + r * self.line_time_s, min(t0 + r * self.line_time_s + exposure, t1))
            for r in range(rows)
        ]
