"""Lens + sensor profiles (``lens_profiles/*.toml``): loading and validation.

A profile describes one lens on one camera: focal length and f-number (the
aperture diameter ``a = f / N`` of Eqs. 2-7), the detector's pixel pitch, size
and shutter (Sec. 6: a rolling shutter's line time), the lens PSF model
(Eq. 3 pillbox or Eq. 4 Gaussian with its constant ``g``) and the focus
mechanism and actuator limits used by motion planning (Sec. 4-8).
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

from pipeline.core.lens import Lens, _where
from pipeline.errors import InputError

_PACKAGE = Path(__file__).resolve().parents[1]
# In a source checkout (and an editable install) the data sits at the top of the repository;
# a wheel carries the same folders as pipeline/_data/<name> (pyproject.toml maps them).
_SHIPPED = {
    "lens_profiles": ("_data/lens_profiles", "../lens_profiles"),
    "sample": ("_data/motorcycle", "../stacks/motorcycle"),
}


def shipped(name: str) -> Path:
    """Where the data shipped with flexdof lives: ``"lens_profiles"`` or ``"sample"``.

    The one lookup for both a wheel install (``pipeline/_data/...``) and a checkout
    (``lens_profiles/``, ``stacks/motorcycle/``).

    >>> (shipped("sample") / "stack.toml").is_file()
    True
    """
    for relative in _SHIPPED[name]:
        candidate = (_PACKAGE / relative).resolve()
        if candidate.is_dir():
            return candidate
    raise InputError(f"the shipped {name} are missing from this install ({_PACKAGE})")


PROFILE_DIR = shipped("lens_profiles")


# TOML schema: table -> {key: Lens field}; required keys are marked True.
_SCHEMA: dict[str | None, dict[str, tuple[str, bool]]] = {
    None: {
        "name": ("name", False),
        "focal_length_mm": ("focal_length_mm", True),
        "f_number": ("f_number", True),
    },
    "sensor": {
        "pixel_pitch_um": ("pixel_pitch_um", True),
        "width_px": ("width_px", True),
        "height_px": ("height_px", True),
        "shutter": ("shutter", False),
        "line_time_us": ("line_time_us", False),
    },
    "psf": {"model": ("psf_model", False), "gaussian_g": ("gaussian_g", False)},
    "focus": {
        "mechanism": ("mechanism", False),
        "step_image_distance_um": ("step_image_distance_um", False),
        "max_speed_mm_s": ("max_speed_mm_s", False),
        "travel_mm": ("travel_mm", False),
    },
}


def available_lenses() -> list[str]:
    """Names (file stems) of the profiles shipped in ``lens_profiles/`` (see :func:`shipped`)."""
    return sorted(p.stem for p in PROFILE_DIR.glob("*.toml"))


def resolve_lens_path(name_or_path: str | Path, *, base_dir: Path | None = None) -> Path:
    """The file a lens name or path refers to (relative paths against ``base_dir``)."""
    text = str(name_or_path)
    candidate = Path(text)
    if base_dir is not None and not candidate.is_absolute():
        candidate = base_dir / candidate
    if candidate.suffix == ".toml" or candidate.exists() or "/" in text:
        if not candidate.is_file():
            raise InputError(f"lens profile {text!r}: no such file ({candidate})")
        return candidate
    profile = PROFILE_DIR / f"{text}.toml"
    if not profile.is_file():
        raise InputError(
            f"unknown lens profile {text!r}: use a file path or one of "
            f"{', '.join(available_lenses())}"
        )
    return profile


def load_lens(name_or_path: str | Path, *, base_dir: Path | None = None) -> Lens:
    """Load a lens profile by name (a stem in ``lens_profiles/``) or path.

    Unknown and missing required keys are :class:`~pipeline.errors.InputError`
    naming the key and the file.
    """
    path = resolve_lens_path(name_or_path, base_dir=base_dir)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise InputError(f"lens profile {path}: cannot read it as TOML: {err}") from err
    return lens_from_dict(data, source=str(path))


def lens_from_dict(data: dict, *, source: str = "") -> Lens:
    """Build a :class:`Lens` from the parsed TOML schema of a lens profile (docs/formats.md)."""
    fields: dict[str, object] = {"source": source, "name": Path(source).stem or "custom lens"}
    for key, value in data.items():
        if isinstance(value, dict):
            if key not in _SCHEMA:
                raise InputError(f"{_where(source)}unknown table [{key}]")
            table = _SCHEMA[key]
            for sub_key, sub_value in value.items():
                if sub_key not in table:
                    raise InputError(
                        f"{_where(source)}unknown key {sub_key!r} in [{key}] "
                        f"(known: {', '.join(table)})"
                    )
                fields[table[sub_key][0]] = sub_value
        elif key in _SCHEMA[None]:
            fields[_SCHEMA[None][key][0]] = value
        else:
            raise InputError(f"{_where(source)}unknown key {key!r}")
    for table_name, table in _SCHEMA.items():
        for key, (field, required) in table.items():
            if required and field not in fields:
                where = f" in [{table_name}]" if table_name else ""
                raise InputError(f"{_where(source)}missing required key {key!r}{where}")
    return Lens(**fields)  # type: ignore[arg-type]


def lens_to_toml(lens: Lens) -> str:
    """Serialise a lens back to the profile schema (for calibration results)."""
    lines = [
        f"name = {_toml_value(lens.name)}",
        f"focal_length_mm = {_toml_value(lens.focal_length_mm)}",
        f"f_number = {_toml_value(lens.f_number)}",
    ]
    for table_name, table in _SCHEMA.items():
        if table_name is None:
            continue
        lines.append(f"\n[{table_name}]")
        for key, (field, _required) in table.items():
            value = getattr(lens, field)
            if value is None or (isinstance(value, float) and math.isinf(value)):
                continue
            lines.append(f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def _toml_value(value: object) -> str:
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)
