"""The lens and sensor of a camera (the paper's four setups are in lens_profiles/):
focal length, f-number, pixel pitch, sensor size, shutter, PSF model, focus drive.
"""

from __future__ import annotations

import dataclasses
import math

from pipeline.core import optics, validate
from pipeline.errors import InputError

SHUTTERS = ("global", "rolling")
PSF_MODELS = ("pillbox", "gaussian")
MECHANISMS = ("detector", "lens")


@dataclasses.dataclass(frozen=True)
class Lens:
    """A lens on a camera body, in millimetres, micrometres, pixels and seconds (docs/formats.md).

    Parameters
    ----------
    focal_length_mm, f_number : float
        Focal length ``f`` and f-number ``N``; the aperture diameter is ``a = f / N``.
    pixel_pitch_um : float
        Detector pixel pitch.
    width_px, height_px : int
        Detector size in pixels.
    shutter : {"global", "rolling"}
        Global shutter, or rolling with ``line_time_us`` between rows (Sec. 6).
    psf_model : {"pillbox", "gaussian"}
        Lens PSF model, Eq. 3 or Eq. 4 (with ``gaussian_g`` as Eq. 4's ``g``).
    mechanism : {"detector", "lens"}
        What moves to focus; the geometry is the same (Sec. 8).
    step_image_distance_um : float or None
        Image-distance change per focus-drive step, where calibrated.
    max_speed_mm_s, travel_mm : float
        Actuator limits used to check planned motions.
    """

    focal_length_mm: float
    f_number: float
    pixel_pitch_um: float
    width_px: int
    height_px: int
    name: str = "custom lens"
    shutter: str = "global"
    line_time_us: float = 0.0
    psf_model: str = "pillbox"
    gaussian_g: float = 1.0
    mechanism: str = "detector"
    step_image_distance_um: float | None = None
    max_speed_mm_s: float = math.inf
    travel_mm: float = math.inf
    source: str = ""

    def __post_init__(self) -> None:
        for field in ("focal_length_mm", "f_number", "pixel_pitch_um", "gaussian_g"):
            _require_positive(field, getattr(self, field), self.source)
        for field in ("width_px", "height_px"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise InputError(
                    f"{_where(self.source)}{field} must be a positive integer, got {value!r}"
                )
        for field, allowed in (
            ("shutter", SHUTTERS),
            ("psf_model", PSF_MODELS),
            ("mechanism", MECHANISMS),
        ):
            if getattr(self, field) not in allowed:
                raise InputError(
                    f"{_where(self.source)}{field} must be one of {', '.join(allowed)}, "
                    f"got {getattr(self, field)!r}"
                )
        _require_non_negative("line_time_us", self.line_time_us, self.source)
        if self.shutter == "rolling" and self.line_time_us <= 0:
            raise InputError(
                f"{_where(self.source)}a rolling shutter needs line_time_us > 0, "
                f"got {self.line_time_us!r}"
            )
        if self.step_image_distance_um is not None:
            _require_positive("step_image_distance_um", self.step_image_distance_um, self.source)
        # an actuator without a speed or travel limit: inf
        _require_positive("max_speed_mm_s", self.max_speed_mm_s, self.source, allow_inf=True)
        _require_positive("travel_mm", self.travel_mm, self.source, allow_inf=True)

    @property
    def aperture_mm(self) -> float:
        """Aperture diameter ``a = f / N`` (Eq. 2)."""
        return self.focal_length_mm / self.f_number

    @property
    def pixel_pitch_mm(self) -> float:
        return self.pixel_pitch_um * 1e-3

    def blur_px(self, image_distance_mm, detector_distance_mm):
        """Blur-circle diameter in pixels, ``a |v - p| / v`` over the pitch (Eq. 2).

        ``image_distance_mm`` is ``v``, where the point focuses; ``detector_distance_mm``
        is the detector's position ``p`` (see :func:`pipeline.core.optics.blur_diameter_mm`).
        """
        b = optics.blur_diameter_mm(self.aperture_mm, image_distance_mm, detector_distance_mm)
        return b / self.pixel_pitch_mm

    @property
    def sensor_height_mm(self) -> float:
        """Detector height ``H`` of Eq. 9."""
        return self.height_px * self.pixel_pitch_mm

    @property
    def readout_time_s(self) -> float:
        """Time between the first and last row's exposure start (rolling shutter, Sec. 6)."""
        return (self.height_px - 1) * self.line_time_us * 1e-6

    def with_f_number(self, f_number: float) -> Lens:
        """The same lens stopped to another f-number."""
        return dataclasses.replace(self, f_number=f_number)


def _where(source: str) -> str:
    return f"{source}: " if source else ""


def _require_positive(name: str, value: object, source: str = "", *, allow_inf=False) -> None:
    validate.positive(name, value, allow_inf=allow_inf, where=_where(source))


def _require_non_negative(name: str, value: object, source: str = "") -> None:
    validate.non_negative(name, value, where=_where(source))
