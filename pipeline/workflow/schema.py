"""Workflow files (TOML): their tables and keys, validated with errors that name the
file and the key (see docs/formats.md).
"""

from __future__ import annotations

import dataclasses
import re
import string
import tomllib
from pathlib import Path

from pipeline.errors import InputError
from pipeline.io.profiles import resolve_lens_path
from pipeline.io.stackfile import check_toml_keys
from pipeline.io.write import WRITE_ENCODINGS
from pipeline.jobs.options import ALIGN_MODELS, ALIGN_MODES, METHODS
from pipeline.workflow.ledger import LEDGER_NAME

_TOP_KEYS = ("description", "inputs", "options", "output", "run", "schedule")
_INPUT_KEYS = ("directories", "files", "frames", "group_by", "options")
_OPTION_KEYS = (
    "lens",
    "method",
    "align",
    "align_model",
    "blur_span_px",
    "white",
    "tile_px",
    "align_max_side_px",
    "frame_guard",
    "frame_range",
    "match_exposure",
    "crop",
)
_OUTPUT_KEYS = ("directory", "name", "encoding")
_RUN_KEYS = ("concurrency", "threads_per_stack", "scheduler", "retry_failed")
_SCHEDULE_KEYS = ("every",)
_NAME_FIELDS = ("stack", "parent")
_UNIT_S = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}


@dataclasses.dataclass(frozen=True)
class InputSpec:
    """One ``[[inputs]]`` table: a glob of stack directories or of frame files."""

    directories: str | None
    files: str | None
    frames: str | None
    group_by: str
    options: dict


@dataclasses.dataclass(frozen=True)
class Workflow:
    """A validated workflow file (paths absolute)."""

    path: Path
    inputs: tuple[InputSpec, ...]
    options: dict
    output_dir: Path
    name_template: str
    encoding: str | None
    concurrency: int | None = None
    threads_per_stack: int | None = None
    scheduler: str | None = None
    retry_failed: bool = False
    every_s: float | None = None
    description: str = ""

    @property
    def name(self) -> str:
        return self.path.stem

    @property
    def ledger_path(self) -> Path:
        return self.output_dir / LEDGER_NAME


# ---------------------------------------------------------------------- parsing
def parse_interval(text: str, *, where: str = "interval") -> float:
    """Seconds in ``"90s"``, ``"15m"``, ``"1h30m"``, ``"1d"`` (a plain number is seconds)."""
    value = text.strip().lower() if isinstance(text, str) else text
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        seconds = float(value)
    elif isinstance(value, str) and re.fullmatch(r"(\d+(\.\d+)?[smhd])+", value):
        seconds = sum(
            float(n) * _UNIT_S[u] for n, _, u in re.findall(r"(\d+(\.\d+)?)([smhd])", value)
        )
    elif isinstance(value, str) and re.fullmatch(r"\d+(\.\d+)?", value):
        seconds = float(value)
    else:
        raise InputError(
            f"{where}: {text!r} is not an interval; write e.g. '90s', '15m', '1h30m' or '1d'"
        )
    if not seconds >= 1:
        raise InputError(f"{where}: {text!r} is shorter than one second")
    return seconds


def _table(path: Path, data: dict, key: str) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise InputError(f"{path}: [{key}] must be a table, got {value!r}")
    return value


def _typed(path: Path, where: str, key: str, value, kind):
    ok = isinstance(value, kind) and not (isinstance(value, bool) and kind is not bool)
    if not ok:
        names = {
            str: "a string",
            int: "an integer",
            bool: "true or false",
            (int, float): "a number",
        }
        raise InputError(f"{path}: {key}{where} must be {names[kind]}, got {value!r}")
    return value


def _parse_options(path: Path, table: dict, where: str) -> dict:
    """Validate an options table (the ``flexdof stack`` flags); lens paths made absolute."""
    check_toml_keys(path, table, _OPTION_KEYS, where)
    options: dict = {}
    for key, value in table.items():
        if key in ("lens", "method", "align", "align_model"):
            _typed(path, where, key, value, str)
        elif key in ("blur_span_px", "white"):
            _typed(path, where, key, value, (int, float))
            if not 0 < value < float("inf"):
                raise InputError(f"{path}: {key}{where} must be a finite number > 0, got {value!r}")
            value = float(value)
        elif key in ("frame_guard", "frame_range", "match_exposure", "crop"):
            _typed(path, where, key, value, bool)
        else:
            _typed(path, where, key, value, int)
            if value < 16:
                raise InputError(f"{path}: {key}{where} must be >= 16 pixels, got {value!r}")
        options[key] = value
    if "method" in options and options["method"] not in METHODS:
        raise InputError(
            f"{path}: method{where} must be one of {', '.join(METHODS)}, got {options['method']!r}"
        )
    if "align" in options and options["align"] not in ALIGN_MODES:
        raise InputError(
            f"{path}: align{where} must be one of {', '.join(ALIGN_MODES)}, "
            f"got {options['align']!r}"
        )
    if "align_model" in options and options["align_model"] not in ALIGN_MODELS:
        raise InputError(
            f"{path}: align_model{where} must be one of {', '.join(ALIGN_MODELS)}, "
            f"got {options['align_model']!r}"
        )
    if "lens" in options:
        try:
            lens_file = resolve_lens_path(options["lens"], base_dir=path.parent)
        except InputError as err:
            raise InputError(f"{path}: lens{where}: {err}") from err
        shipped = lens_file.parent.name == "lens_profiles" and lens_file.stem == options["lens"]
        options["lens"] = options["lens"] if shipped else str(lens_file.resolve())
    return options


def _parse_input(path: Path, index: int, table: object) -> InputSpec:
    where = f" in [[inputs]] #{index + 1}"
    if not isinstance(table, dict):
        raise InputError(f"{path}: [[inputs]] #{index + 1} must be a table")
    check_toml_keys(path, table, _INPUT_KEYS, where)
    given = [key for key in ("directories", "files") if key in table]
    if len(given) != 1:
        raise InputError(
            f"{path}: give exactly one of 'directories' (a glob of stack folders) "
            f"or 'files' (a glob of frames grouped into stacks){where}"
        )
    for key in ("directories", "files", "frames", "group_by"):
        if key in table:
            _typed(path, where, key, table[key], str)
            if not table[key]:
                raise InputError(f"{path}: {key}{where} is empty")
    if "frames" in table and "directories" not in table:
        raise InputError(
            f"{path}: 'frames'{where} (a pattern inside each directory) needs 'directories'"
        )
    if "group_by" in table and "files" not in table:
        raise InputError(f"{path}: 'group_by'{where} needs 'files'")
    if "frames" in table and ("/" in table["frames"] or table["frames"].startswith(".")):
        raise InputError(
            f"{path}: frames{where} is a file-name pattern inside each stack "
            f"directory, got {table['frames']!r}"
        )
    group_by = table.get("group_by", "directory")
    if group_by != "directory":
        try:
            regex = re.compile(group_by)
        except re.error as err:
            raise InputError(
                f"{path}: group_by{where} is not a regular expression ({err}); "
                "use 'directory' or a regex with a group named 'stack'"
            ) from err
        if "stack" not in regex.groupindex:
            raise InputError(
                f"{path}: group_by{where} needs a named group (?P<stack>...), got {group_by!r}"
            )
    options = _parse_options(
        path, _table(path, table, "options"), f" in [inputs.options] of [[inputs]] #{index + 1}"
    )
    return InputSpec(
        table.get("directories"), table.get("files"), table.get("frames"), group_by, options
    )


def load_workflow(path: str | Path, *, overrides: dict | None = None) -> Workflow:
    """Read and validate a workflow file.

    Parameters
    ----------
    path : str or Path
        The TOML file; relative paths in it are relative to its folder.
    overrides : dict, optional
        Options (``_OPTION_KEYS``) and ``[run]`` keys given on the command line;
        they win over the file.

    Raises
    ------
    InputError
        Naming the file, the key and the fix.
    """
    path = Path(path).resolve()
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise InputError(f"workflow {path}: cannot read it ({err.strerror or err})") from err
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise InputError(f"workflow {path}: not valid TOML: {err}") from err
    check_toml_keys(path, data, _TOP_KEYS, "")
    overrides = dict(overrides or {})

    tables = data.get("inputs")
    if not isinstance(tables, list) or not tables:
        raise InputError(
            f"{path}: needs at least one [[inputs]] table with 'directories' or 'files'"
        )
    inputs = tuple(_parse_input(path, i, table) for i, table in enumerate(tables))

    option_overrides = {k: overrides.pop(k) for k in _OPTION_KEYS if k in overrides}
    options = _parse_options(
        path, {**_table(path, data, "options"), **option_overrides}, " in [options]"
    )

    output = _table(path, data, "output")
    check_toml_keys(path, output, _OUTPUT_KEYS, " in [output]")
    if "directory" not in output:
        raise InputError(f"{path}: missing key 'directory' in [output] (where results go)")
    directory = _typed(path, " in [output]", "directory", output["directory"], str)
    output_dir = (path.parent / directory).resolve()
    template = _typed(path, " in [output]", "name", output.get("name", "{stack}.tif"), str)
    _check_template(path, template)
    encoding = output.get("encoding")
    ext = Path(template).suffix.lower()
    if encoding is not None:
        _typed(path, " in [output]", "encoding", encoding, str)
        if encoding not in WRITE_ENCODINGS[ext]:
            raise InputError(
                f"{path}: encoding {encoding!r} in [output] is not available for "
                f"{ext} outputs; use one of {', '.join(WRITE_ENCODINGS[ext])}"
            )

    run = _table(path, data, "run")
    check_toml_keys(path, run, _RUN_KEYS, " in [run]")
    run.update({k: v for k, v in overrides.items() if k in _RUN_KEYS and v is not None})
    for key in ("concurrency", "threads_per_stack"):
        if key in run and _typed(path, " in [run]", key, run[key], int) < 1:
            raise InputError(f"{path}: {key} in [run] must be >= 1, got {run[key]!r}")
    scheduler = run.get("scheduler")
    if scheduler is not None:
        _typed(path, " in [run]", "scheduler", scheduler, str)
        if "://" not in scheduler:
            raise InputError(
                f"{path}: scheduler in [run] must be an address like "
                f"tcp://host:8786, got {scheduler!r}"
            )
    retry = _typed(path, " in [run]", "retry_failed", run.get("retry_failed", False), bool)

    schedule = _table(path, data, "schedule")
    check_toml_keys(path, schedule, _SCHEDULE_KEYS, " in [schedule]")
    every = schedule.get("every")
    every_s = None if every is None else parse_interval(every, where=f"{path}: every in [schedule]")
    description = _typed(path, "", "description", data.get("description", ""), str)
    return Workflow(
        path,
        inputs,
        options,
        output_dir,
        template,
        encoding,
        run.get("concurrency"),
        run.get("threads_per_stack"),
        scheduler,
        retry,
        every_s,
        description,
    )


def _check_template(path: Path, template: str) -> None:
    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(template) if f is not None]
    except ValueError as err:
        raise InputError(f"{path}: name in [output] {template!r}: {err}") from err
    for field in fields:
        if field not in _NAME_FIELDS:
            raise InputError(
                f"{path}: name in [output] uses {{{field}}}; the fields are "
                + ", ".join(f"{{{f}}}" for f in _NAME_FIELDS)
            )
    if "stack" not in fields:
        raise InputError(f"{path}: name in [output] must contain {{stack}}, got {template!r}")
    if Path(template).suffix.lower() not in WRITE_ENCODINGS:
        raise InputError(
            f"{path}: name in [output] must end in one of "
            f"{', '.join(WRITE_ENCODINGS)}, got {template!r}"
        )
    if Path(template).is_absolute() or ".." in Path(template).parts:
        raise InputError(
            f"{path}: name in [output] must be a relative name inside the output "
            f"directory, got {template!r}"
        )
