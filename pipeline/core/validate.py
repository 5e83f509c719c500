"""Checks of numeric parameters, one rule each, with errors that name the parameter.

Every layer validates user-facing numbers through these, so the same kind of value
gets the same rule and the same message everywhere: ``"{where}{name} must be ...,
got {value!r}"``, where ``where`` names the file or flag the value came from
(e.g. ``"stack.toml: "``). Booleans are never numbers; NaN never passes.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from pipeline.errors import InputError


def _fail(name: str, rule: str, value: object, where: str) -> InputError:
    return InputError(f"{where}{name} must be {rule}, got {value!r}")


def _real(value: object) -> float | None:
    """``value`` as a float if it is a real number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    return float(value)


def positive(name: str, value: object, *, allow_inf: bool = False, where: str = "") -> float:
    """A number > 0 (finite unless ``allow_inf``).

    Examples
    --------
    >>> positive("exposure_s", 0.5)
    0.5
    >>> positive("exposure_s", 0)
    Traceback (most recent call last):
    ...
    pipeline.errors.InputError: exposure_s must be > 0, got 0
    """
    x = _real(value)
    if x is None or math.isnan(x) or x <= 0:
        raise _fail(name, "> 0", value, where)
    if math.isinf(x) and not allow_inf:
        raise _fail(name, "a finite number > 0", value, where)
    return x


def non_negative(name: str, value: object, *, where: str = "") -> float:
    """A finite number >= 0."""
    x = _real(value)
    if x is None or not 0 <= x < math.inf:
        raise _fail(name, "a finite number >= 0", value, where)
    return x


def finite(name: str, value: object, *, where: str = "") -> float:
    """A finite number."""
    x = _real(value)
    if x is None or not math.isfinite(x):
        raise _fail(name, "a finite number", value, where)
    return x


def whole(name: str, value: object, *, minimum: int = 1, where: str = "") -> int:
    """An integer >= ``minimum`` (numpy integers count; floats and bools do not)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < minimum:
        raise _fail(name, f"an integer >= {minimum}", value, where)
    return int(value)


def positive_array(name: str, value: object) -> np.ndarray:
    """An array (or number) of values > 0 as float64; infinities allowed, NaN not."""
    arr = np.asarray(value, dtype=np.float64)
    if np.any(np.isnan(arr)):
        raise InputError(f"{name} must not be NaN, got {value!r}")
    if np.any(arr <= 0):
        raise InputError(f"{name} must be > 0, got {value!r}")
    return arr
