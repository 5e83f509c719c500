"""The Stack model: frames + focus positions, the ``stack.toml`` sidecar, lazy reading.

A focal stack (Sec. 9) is a set of frames shot at different focus settings;
the weights that emulate a constant-speed detector sweep need each frame's
image distance ``v`` (Eq. 1). A sweep capture (Sec. 4, 8) is one frame plus
the motion during its exposure. ``stack.toml`` (docs/formats.md) gives the lens and
each frame's focus position; without it, frames are taken in natural file-name
order and positions come from EXIF SubjectDistance when every frame has one,
else they are unknown (the caller estimates them from the magnification).

Frames are read one at a time (:meth:`Stack.read`); the jobs stream them through
:mod:`pipeline.parallel.accumulate`, so a stack never has to fit in memory.
"""

from __future__ import annotations

import dataclasses
import glob
import json
import logging
import math
import re
import tomllib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pipeline.core import optics
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile
from pipeline.errors import InputError
from pipeline.io.exif import subject_distance_mm
from pipeline.io.probe import (
    IMAGE_EXTENSIONS,
    RAW_EXTENSIONS,
    FrameInfo,
    frame_info,
    supported_extensions,
)
from pipeline.io.profiles import load_lens
from pipeline.io.read import read_frame

log = logging.getLogger(__name__)

SIDECAR = "stack.toml"
MAX_IMAGE_DISTANCE_F = 100  # v <= 100 f: magnification 99x, beyond any bellows or macro lens
KINDS = ("focal-stack", "sweep")
POSITION_KEYS = ("focus_distance_mm", "image_distance_mm", "focus_step")
SWEEP_PROFILES = ("constant-speed",)
_TOP_KEYS = ("lens", "kind", "partial", "white", "frames", "sweep")
_FRAME_KEYS = ("file", *POSITION_KEYS)
_SWEEP_PAIRS = (
    ("start_image_distance_mm", "end_image_distance_mm"),
    ("start_focus_distance_mm", "end_focus_distance_mm"),
    ("start_focus_step", "end_focus_step"),  # tethered sweeps (flexdof tether sweep)
)
_SWEEP_KEYS = ("file", *(key for pair in _SWEEP_PAIRS for key in pair), "exposure_s", "profile")


@dataclasses.dataclass(frozen=True)
class Frame:
    """One frame: its file and at most one focus position.

    Parameters
    ----------
    file : Path
        The image file.
    focus_distance_mm : float, optional
        Object distance ``u`` in focus (``math.inf`` allowed).
    image_distance_mm : float, optional
        Lens-to-detector distance ``v`` (Eq. 1).
    focus_step : float, optional
        Focus-drive position in motor steps (relative; see :func:`image_distances_mm`).
    """

    file: Path
    focus_distance_mm: float | None = None
    image_distance_mm: float | None = None
    focus_step: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "file", Path(self.file))
        given = [key for key in POSITION_KEYS if getattr(self, key) is not None]
        if len(given) > 1:
            raise InputError(
                f"frame {self.file}: give exactly one of {', '.join(POSITION_KEYS)}, "
                f"got {' and '.join(given)}"
            )

    @property
    def position_kind(self) -> str | None:
        """Which position key is set, or None."""
        return next((key for key in POSITION_KEYS if getattr(self, key) is not None), None)


@dataclasses.dataclass(frozen=True)
class Sweep:
    """The motion during a focus-sweep exposure (``[sweep]`` of stack.toml).

    Exactly one pair of ends is given: image distances or focus distances.
    """

    file: Path
    exposure_s: float
    start_image_distance_mm: float | None = None
    end_image_distance_mm: float | None = None
    start_focus_distance_mm: float | None = None
    end_focus_distance_mm: float | None = None
    start_focus_step: float | None = None
    end_focus_step: float | None = None
    profile: str = "constant-speed"


@dataclasses.dataclass(frozen=True)
class Stack:
    """A focal stack or a sweep capture.

    Parameters
    ----------
    frames : tuple of Frame
        Frames in natural file-name order (a sweep has its one capture here).
    lens : str, optional
        Lens profile name or path as written in stack.toml.
    lens_profile : Lens, optional
        That profile, loaded (relative paths against ``base_dir``).
    kind : {"focal-stack", "sweep"}
    sweep : Sweep, optional
        The motion, for ``kind == "sweep"``.
    base_dir : Path
        The stack directory (or the first file's directory).
    partial : bool
        True when stack.toml marks an interrupted capture.
    positions_source : {"stack.toml", "exif"}, optional
        Where the frames' focus positions came from; None when unknown.
    white : float, optional
        The value of white in the frames, for float TIFF frames in other units than
        white at 1 (``white`` in stack.toml; see :func:`pipeline.io.read.read_frame`).
    """

    frames: tuple[Frame, ...]
    base_dir: Path
    lens: str | None = None
    lens_profile: Lens | None = None
    kind: str = "focal-stack"
    sweep: Sweep | None = None
    partial: bool = False
    positions_source: str | None = None
    white: float | None = None

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def files(self) -> list[Path]:
        return [frame.file for frame in self.frames]

    def read(self, index: int) -> np.ndarray:
        """Decode frame ``index`` (float32 linear light)."""
        return read_frame(self.frames[index].file, white=self.white)


def natural_key(path: str | Path) -> list:
    """Sort key putting ``pcb_2`` before ``pcb_10`` (digit runs compare as numbers)."""
    parts = re.split(r"(\d+)", str(path))
    return [(0, int(part), "") if part.isdigit() else (1, 0, part.lower()) for part in parts]


# File names of finished results rather than frames (another tool's output, a reference).
_RESULT_NAME_RE = re.compile(
    r"^(expected|result|results|output|stacked|edof|ground[_-]?truth|reference)([_.-]|$)"
    r"|_edof([_.-]|$)|[_-](stacked|result|expected)$",
    re.IGNORECASE,
)


def is_flexdof_result(path: Path) -> bool:
    """True when ``path`` has a flexdof result sidecar beside it (``path.json`` with inputs)."""
    sidecar = path.with_name(path.name + ".json")
    if not sidecar.is_file():
        return False
    try:
        data = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(data, dict) and "inputs" in data and "version" in data


def looks_like_result(path: Path) -> bool:
    """True for names such as ``expected.jpg``, ``result.png``, ``pcb_edof.tif``; a numbered
    name (``output_0001.png``, as video-frame extractors write) is a frame."""
    stem = Path(path).stem
    return bool(_RESULT_NAME_RE.search(stem)) and not re.search(r"\d$", stem)


def _drop_results(files: list[Path], where: str) -> list[Path]:
    """Leave out flexdof's own outputs and files named like another tool's result (logged)."""
    kept = []
    named = [file for file in files if looks_like_result(file)]
    if len(files) - len(named) < max(2, len(named) + 1):
        named = []  # most files are named so: they are the frames
    for file in files:
        if is_flexdof_result(file):
            log.warning(
                "%s: skipping %s: it is a flexdof result (it has %s.json), not a frame",
                where, file.name, file.name,
            )
        elif file in named:
            log.warning(
                "%s: skipping %s: its name looks like a finished result, not a frame; "
                "name the file on the command line, or list it in stack.toml, to use it",
                where, file.name,
            )
        else:
            kept.append(file)
    return kept


def _one_format_per_shot(files: list[Path], where: str) -> list[Path]:
    """The RAW files where every shot is there as RAW and as JPEG/TIFF (RAW+JPEG).

    Cameras set to RAW+JPEG write ``IMG_0001.CR2`` beside ``IMG_0001.JPG``; stacking
    both would take each shot twice, in two sizes and encodings. The RAW files are
    linear light, what the weighted average of Sec. 9 sums, so they are the frames
    (logged). Other twins (the same shots exported twice) are refused by name.
    """
    shots: dict[str, list[Path]] = {}
    for file in sorted(files, key=natural_key):
        shots.setdefault(file.stem.lower(), []).append(file)
    twins = [group for group in shots.values() if len(group) > 1]
    if not twins:
        return files
    raws = [[f for f in group if f.suffix.lower() in RAW_EXTENSIONS] for group in shots.values()]
    first = twins[0]
    if all(len(raw) == 1 for raw in raws):
        other = next(f for f in first if f.suffix.lower() not in RAW_EXTENSIONS)
        log.warning(
            "%s: each shot is there as RAW and as %s (%s); stacking the %d RAW files "
            "(name the others, e.g. '%s', to stack them instead)",
            where, other.suffix, ", ".join(f.name for f in first), len(raws),
            Path(where) / f"*{other.suffix}",
        )
        return [raw[0] for raw in raws]
    raise InputError(
        f"{where}: {first[0].stem} is there {len(first)} times "
        f"({', '.join(f.name for f in first)}): the same shots in two formats? name one "
        f"kind, e.g. '{Path(where) / ('*' + first[0].suffix)}'"
    )


def _images_in(directory: Path) -> list[Path]:
    found = [
        p
        for p in directory.iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and not p.name.startswith(".")
    ]  # hidden files: a Mac's "._IMG_0001.JPG" resource forks on a card, partial downloads
    files = _one_format_per_shot(_drop_results(found, str(directory)), str(directory))
    if not files:
        skipped = f" (skipped {len(found)} result file(s))" if found else ""
        raise InputError(
            f"no image files in {directory}{skipped}; supported: {supported_extensions()}"
        )
    return sorted(files, key=natural_key)


def _expand(entry: str | Path) -> list[Path]:
    """One command-line entry: an image file or a glob of image files."""
    text = str(entry)
    if any(ch in text for ch in "*?["):
        matches = [Path(m) for m in glob.glob(text) if Path(m).is_file()]
        images = [p for p in matches if p.suffix.lower() in IMAGE_EXTENSIONS]
        images = _drop_results(images, text)
        if not images:
            raise InputError(
                f"{text}: the pattern matches no image files; supported: {supported_extensions()}"
            )
        return sorted(images, key=natural_key)
    path = Path(text)
    if path.is_dir():
        raise InputError(f"{path} is a directory: pass one directory alone, or files and globs")
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    if path.suffix.lower() not in IMAGE_EXTENSIONS:
        raise InputError(
            f"{path}: not a supported image extension; supported: {supported_extensions()}"
        )
    return [path]


def _reject_duplicates(files: Sequence[Path], where: str) -> None:
    seen: dict[Path, Path] = {}
    for file in files:
        resolved = file.resolve()
        if resolved in seen:
            raise InputError(f"{where}: {file} is listed twice (also as {seen[resolved]})")
        seen[resolved] = file


def load_stack(paths: str | Path | Sequence[str | Path]) -> Stack:
    """Build a :class:`Stack` from a directory, a ``stack.toml``, globs or files.

    Parameters
    ----------
    paths : path or sequence of paths
        One directory (its ``stack.toml`` if present, else every image file in
        it), one ``stack.toml``, or image files and glob patterns (kept in
        natural file-name order). Directories and globs leave out flexdof's own
        results (an image with a result sidecar ``NAME.json`` beside it) and
        files named like another tool's result (``expected.jpg``,
        ``result.png``, ``*_edof.tif``, ``stacked.tif``, ...), with a warning;
        name such a file explicitly to use it as a frame. A directory leaves out
        hidden files (``._IMG_0001.JPG``) and, where every shot is there as RAW and
        as JPEG or TIFF, the latter (``_one_format_per_shot``).

    Raises
    ------
    InputError
        Empty directories, missing or duplicate files, unsupported extensions
        and every sidecar error, naming the file and the key.
    """
    entries = [paths] if isinstance(paths, (str, Path)) else list(paths)
    if not entries:
        raise InputError("no input given: pass a stack directory, a stack.toml, files or globs")
    if len(entries) == 1:
        single = Path(entries[0])
        if single.is_dir():
            if (single / SIDECAR).is_file():
                return _load_sidecar(single / SIDECAR)
            return _stack_from_files(_images_in(single), single)
        if single.is_file() and single.suffix.lower() == ".toml":
            return _load_sidecar(single)
    files = [file for entry in entries for file in _expand(entry)]
    _reject_duplicates(files, "inputs")
    return _stack_from_files(files, files[0].parent)


def _stack_from_files(files: list[Path], base_dir: Path) -> Stack:
    """A sidecar-less focal stack; focus distances from EXIF when every frame has one."""
    distances = [subject_distance_mm(file) for file in files]
    if all(d is not None for d in distances):
        frames = tuple(Frame(f, focus_distance_mm=d) for f, d in zip(files, distances))
        return Stack(frames, base_dir, positions_source="exif")
    return Stack(tuple(Frame(f) for f in files), base_dir)


# --- stack.toml ------------------------------------------------------------------------------


def _number(toml: Path, key: str, value: object, *, allow_inf: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{toml}: {key} must be a number, got {value!r}")
    number = float(value)
    if math.isnan(number) or (math.isinf(number) and not (allow_inf and number > 0)):
        raise InputError(f"{toml}: {key} must be a finite number, got {value!r}")
    return number


def _positive(toml: Path, key: str, value: object, *, allow_inf: bool = False) -> float:
    number = _number(toml, key, value, allow_inf=allow_inf)
    if number <= 0:
        raise InputError(f"{toml}: {key} must be > 0, got {value!r}")
    return number


def check_toml_keys(toml: Path, table: dict, known: Sequence[str], where: str) -> None:
    """Refuse keys of a TOML table that the schema does not know, naming file and key."""
    for key in table:
        if key not in known:
            raise InputError(f"{toml}: unknown key {key!r}{where} (known: {', '.join(known)})")


def _sidecar_file(toml: Path, base: Path, value: object, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise InputError(f"{toml}: 'file'{where} must be a file name, got {value!r}")
    path = base / value
    if not path.is_file():
        raise InputError(f"{toml}: 'file'{where}: {path} does not exist")
    if path.suffix.lower() not in IMAGE_EXTENSIONS:
        raise InputError(
            f"{toml}: 'file'{where}: {value!r} is not a supported image; "
            f"supported: {supported_extensions()}"
        )
    return path


def _parse_frame(toml: Path, base: Path, index: int, table: object) -> Frame:
    where = f" in [[frames]] #{index + 1}"
    if not isinstance(table, dict):
        raise InputError(f"{toml}: [[frames]] #{index + 1} must be a table")
    check_toml_keys(toml, table, _FRAME_KEYS, where)
    if "file" not in table:
        raise InputError(f"{toml}: missing key 'file'{where}")
    file = _sidecar_file(toml, base, table["file"], where)
    given = [key for key in POSITION_KEYS if key in table]
    if len(given) > 1:
        raise InputError(
            f"{toml}: frame {table['file']!r} has {' and '.join(given)}; give exactly one of "
            f"{', '.join(POSITION_KEYS)}"
        )
    values: dict[str, float] = {}
    for key in given:
        label = f"{key} of frame {table['file']!r}"
        if key == "focus_step":
            values[key] = _number(toml, label, table[key])
        else:
            inf_ok = key == "focus_distance_mm"
            values[key] = _positive(toml, label, table[key], allow_inf=inf_ok)
    return Frame(file, **values)


def _parse_sweep(toml: Path, base: Path, table: object) -> Sweep:
    if not isinstance(table, dict):
        raise InputError(f"{toml}: [sweep] must be a table")
    check_toml_keys(toml, table, _SWEEP_KEYS, " in [sweep]")
    for key in ("file", "exposure_s"):
        if key not in table:
            raise InputError(f"{toml}: missing key {key!r} in [sweep]")
    pairs = [pair for pair in _SWEEP_PAIRS if any(key in table for key in pair)]
    if len(pairs) != 1 or not all(key in table for key in pairs[0]):
        raise InputError(
            f"{toml}: [sweep] needs exactly one pair of ends: "
            + " or ".join(" and ".join(pair) for pair in _SWEEP_PAIRS)
        )
    profile = table.get("profile", "constant-speed")
    if profile not in SWEEP_PROFILES:
        raise InputError(
            f"{toml}: profile in [sweep] must be one of {', '.join(SWEEP_PROFILES)}, "
            f"got {profile!r}"
        )
    inf_ok = pairs[0] is _SWEEP_PAIRS[1]
    if pairs[0] is _SWEEP_PAIRS[2]:  # drive steps: any finite numbers
        ends = {key: _number(toml, key, table[key]) for key in pairs[0]}
    else:
        ends = {key: _positive(toml, key, table[key], allow_inf=inf_ok) for key in pairs[0]}
    return Sweep(
        file=_sidecar_file(toml, base, table["file"], " in [sweep]"),
        exposure_s=_positive(toml, "exposure_s", table["exposure_s"]),
        profile=profile,
        **ends,
    )


def _load_sidecar(toml: Path) -> Stack:
    base = toml.parent
    try:
        data = tomllib.loads(toml.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise InputError(f"{toml}: cannot read it as TOML: {err}") from err
    check_toml_keys(toml, data, _TOP_KEYS, "")
    kind = data.get("kind", "focal-stack")
    if kind not in KINDS:
        raise InputError(f"{toml}: kind must be one of {', '.join(KINDS)}, got {kind!r}")
    partial = data.get("partial", False)
    if not isinstance(partial, bool):
        raise InputError(f"{toml}: partial must be true or false, got {partial!r}")
    if partial:
        log.warning("%s: partial = true: this capture was interrupted; frames may be missing", toml)
    white = data.get("white")
    if white is not None:
        white = _positive(toml, "white", white)
    lens_name = data.get("lens")
    lens = None
    if lens_name is not None:
        if not isinstance(lens_name, str) or not lens_name:
            raise InputError(f"{toml}: lens must be a profile name or path, got {lens_name!r}")
        try:
            lens = load_lens(lens_name, base_dir=base)
        except InputError as err:
            raise InputError(f"{toml}: lens = {lens_name!r}: {err}") from err

    sweep = None
    if kind == "sweep":
        if "frames" in data:
            raise InputError(f"{toml}: kind = 'sweep' takes a [sweep] table, not [[frames]]")
        if "sweep" not in data:
            raise InputError(f"{toml}: kind = 'sweep' needs a [sweep] table")
        sweep = _parse_sweep(toml, base, data["sweep"])
        frames: tuple[Frame, ...] = (Frame(sweep.file),)
        positions_source = None
    else:
        if "sweep" in data:
            raise InputError(f"{toml}: [sweep] needs kind = 'sweep'")
        tables = data.get("frames")
        if not isinstance(tables, list) or not tables:
            raise InputError(f"{toml}: a focal stack needs at least one [[frames]] table")
        parsed = [_parse_frame(toml, base, i, table) for i, table in enumerate(tables)]
        _reject_duplicates([frame.file for frame in parsed], str(toml))
        frames = tuple(sorted(parsed, key=lambda frame: natural_key(frame.file)))
        positions_source = _check_positions(toml, frames)
    stack = Stack(
        frames,
        base,
        lens=lens_name,
        lens_profile=lens,
        kind=kind,
        sweep=sweep,
        partial=partial,
        positions_source=positions_source,
        white=white,
    )
    if lens is not None:
        _check_against_lens(toml, stack, lens)
    return stack


def _check_positions(toml: Path, frames: Sequence[Frame]) -> str | None:
    """All frames have a position or none does; motor steps are not mixed with distances."""
    kinds = [frame.position_kind for frame in frames]
    if all(kind is None for kind in kinds):
        return None
    missing = [frame.file.name for frame, kind in zip(frames, kinds) if kind is None]
    if missing:
        raise InputError(
            f"{toml}: frame {missing[0]!r} has no focus position but others do; give one of "
            f"{', '.join(POSITION_KEYS)} for every frame or for none"
        )
    if "focus_step" in kinds and set(kinds) != {"focus_step"}:
        raise InputError(
            f"{toml}: focus_step (relative motor steps) cannot be mixed with absolute "
            "focus_distance_mm/image_distance_mm; use one or the other for all frames"
        )
    return "stack.toml"


def _check_against_lens(toml: Path, stack: Stack, lens: Lens) -> None:
    """Focus distances must exceed f and image distances must be >= f (Eq. 1)."""
    f = lens.focal_length_mm
    checks: list[tuple[str, str, float | None]] = [
        (frame.file.name, "focus_distance_mm", frame.focus_distance_mm) for frame in stack.frames
    ]
    checks += [
        (frame.file.name, "image_distance_mm", frame.image_distance_mm) for frame in stack.frames
    ]
    if stack.sweep is not None:
        sweep = stack.sweep
        for key in (*_SWEEP_PAIRS[0], *_SWEEP_PAIRS[1]):
            checks.append(("[sweep]", key, getattr(sweep, key)))
    for name, key, value in checks:
        if value is None:
            continue
        if "focus_distance" in key and value <= f:
            raise InputError(
                f"{toml}: {key} = {value} of {name} must exceed the focal length {f} mm of "
                f"lens {stack.lens!r} (nothing nearer than f forms a real image)"
            )
        if "image_distance" in key and value < f:
            raise InputError(
                f"{toml}: {key} = {value} of {name} is less than the focal length {f} mm of "
                f"lens {stack.lens!r}; the image distance of a real image is >= f"
            )
        if "image_distance" in key and value > MAX_IMAGE_DISTANCE_F * f:
            raise InputError(
                f"{toml}: {key} = {value} of {name} is {value / f:.3g} times the focal length "
                f"{f} mm of lens {stack.lens!r} (a magnification of {value / f - 1:.3g}x); the "
                f"image distance is the lens-to-detector distance in mm, at most "
                f"{MAX_IMAGE_DISTANCE_F} f"
            )


# --- checks and derived quantities -----------------------------------------------------------


def check_frames(stack: Stack) -> FrameInfo:
    """Check from the headers that all frames have one size and channel count.

    Returns
    -------
    FrameInfo
        The common shape.

    Raises
    ------
    InputError
        Naming the first odd file, its size and the expected size (of the first frame).
    """
    expected = frame_info(stack.frames[0].file)
    for frame in stack.frames[1:]:
        info = frame_info(frame.file)
        if info != expected:
            turned = (info.cols, info.rows) == (expected.rows, expected.cols)
            hint = (
                " (it is stored turned a quarter against the others, e.g. rotated and saved "
                "again by a viewer: export every frame alike, as the camera stored them)"
                if turned
                else ""
            )
            raise InputError(
                f"{frame.file}: {info.describe()}, but {stack.frames[0].file.name} and the "
                f"stack expect {expected.describe()}; all frames must have one size{hint}"
            )
    return expected


@dataclasses.dataclass(frozen=True)
class FocusPositions:
    """Per-frame image distances ``v`` (mm).

    ``relative`` is True when only differences are known (focus-drive steps):
    then ``image_distances_mm[i]`` is ``v_i - v_0`` for the first frame,
    ``(step_i - step_0) * step_image_distance_um / 1000``; the absolute offset
    is unknown.
    """

    image_distances_mm: np.ndarray
    relative: bool


def _require_lens(stack: Stack, lens: Lens | None, need: str) -> Lens:
    lens = lens if lens is not None else stack.lens_profile
    if lens is None:
        raise InputError(f"{stack.base_dir}: {need} needs a lens profile: set lens in stack.toml")
    return lens


def image_distances_mm(stack: Stack, lens: Lens | None = None) -> FocusPositions | None:
    """Each frame's image distance from its focus position (Eq. 1), or None if unknown.

    Parameters
    ----------
    stack : Stack
    lens : Lens, optional
        Defaults to the stack's lens profile; needed for focus distances
        (``v = f u / (u - f)``) and focus steps (``step_image_distance_um``).

    Returns
    -------
    FocusPositions or None
        None when no frame has a position (estimate them from the magnification).
    """
    kinds = {frame.position_kind for frame in stack.frames}
    if kinds == {None}:
        return None
    if "focus_step" in kinds:
        lens = _require_lens(stack, lens, "focus_step")
        if lens.step_image_distance_um is None:
            raise InputError(
                f"lens {lens.name!r} ({lens.source}) has no step_image_distance_um: calibrate "
                "the focus drive (flexdof tether calibrate) or give image distances"
            )
        steps = np.array([frame.focus_step for frame in stack.frames], dtype=np.float64)
        return FocusPositions((steps - steps[0]) * lens.step_image_distance_um * 1e-3, True)
    values = []
    for frame in stack.frames:
        if frame.image_distance_mm is not None:
            values.append(frame.image_distance_mm)
        else:
            f = _require_lens(stack, lens, "focus_distance_mm").focal_length_mm
            values.append(float(optics.image_distance(f, frame.focus_distance_mm)))  # Eq. 1
    return FocusPositions(np.array(values, dtype=np.float64), False)


def sweep_profile(stack: Stack, lens: Lens | None = None) -> Profile:
    """The detector motion p(t) of a sweep capture (constant speed, Sec. 4.1).

    Focus-distance ends are converted to image distances with Eq. 1. Focus-drive
    steps (``+`` = towards far) need the lens's ``step_image_distance_um`` and give
    only relative positions: the far end is placed at infinity focus (``p = f``).
    The IPSF depends on the blur swept, ``a dp / (p pitch)``, so the unknown offset
    changes it by about ``dp / f`` (a few % for a focus ring's travel).
    """
    sweep = stack.sweep
    if stack.kind != "sweep" or sweep is None:
        raise InputError(f"{stack.base_dir}: not a sweep capture (kind = {stack.kind!r})")
    if sweep.start_image_distance_mm is not None:
        start, end = sweep.start_image_distance_mm, sweep.end_image_distance_mm
    elif sweep.start_focus_step is not None:
        lens = _require_lens(stack, lens, "a focus-step sweep")
        if lens.step_image_distance_um is None:
            raise InputError(
                f"lens {lens.name!r} ({lens.source}) has no step_image_distance_um: calibrate "
                "the focus drive (flexdof tether calibrate) to deconvolve a focus-step sweep"
            )
        far = max(sweep.start_focus_step, sweep.end_focus_step)
        step_mm = lens.step_image_distance_um * 1e-3
        start = lens.focal_length_mm + (far - sweep.start_focus_step) * step_mm
        end = lens.focal_length_mm + (far - sweep.end_focus_step) * step_mm
    else:
        f = _require_lens(stack, lens, "a focus-distance sweep").focal_length_mm
        start = float(optics.image_distance(f, sweep.start_focus_distance_mm))  # Eq. 1
        end = float(optics.image_distance(f, sweep.end_focus_distance_mm))  # Eq. 1
    return Profile([0.0, sweep.exposure_s], [start, end])  # p(t) = p0 + s t
