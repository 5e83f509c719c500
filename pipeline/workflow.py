"""Workflow files (``workflows/*.toml``): many stacks, incremental and scheduled runs.

A workflow names its inputs (globs of stack directories, or of frame files
grouped into stacks), the options of the main job (Sec. 9 / Sec. 4 pipeline:
lens, alignment, deconvolution method), where the outputs go and how they are
named, the concurrency and an optional schedule. The whole file is validated
(unknown keys, types, inputs that match nothing, output names that would leave
the output directory or collide) before any work starts.

A run (:func:`run_workflow`) processes only stacks whose *fingerprint* -- the
SHA-256 of every input file's content, the options, the output name and the
flexdof version -- differs from the ledger's last completed one, records every
stack in the ledger (:mod:`pipeline.ledger`) and holds the output directory's
run lock throughout. The commented examples in ``workflows/`` document the
schema.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import json
import logging
import re
import string
import threading
import time
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path

from pipeline import __version__
from pipeline.batch import BatchJob, OnProgress, run_batch
from pipeline.engine import ALIGN_MODES, METHODS, StackOptions
from pipeline.errors import FlexdofError, InputError
from pipeline.io import IMAGE_EXTENSIONS, WRITE_ENCODINGS
from pipeline.ledger import LEDGER_NAME, Ledger, RunLock
from pipeline.profiles import resolve_lens_path
from pipeline.stack import check_toml_keys, load_stack, natural_key

log = logging.getLogger(__name__)

_TOP_KEYS = ("description", "inputs", "options", "output", "run", "schedule")
_INPUT_KEYS = ("directories", "files", "frames", "group_by", "options")
_OPTION_KEYS = ("lens", "method", "align", "blur_span_px", "tile_px", "align_max_side_px")
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


@dataclasses.dataclass(frozen=True)
class PlannedStack:
    """One stack found by a workflow's inputs."""

    id: str  # ledger key: the stack's directory (or group) relative to the workflow file
    paths: tuple[str, ...]  # what load_stack takes
    output: Path
    options: StackOptions
    watch: tuple[Path, ...]  # files whose content defines the stack (fingerprint)
    base: Path  # the stack's folder (file names in the fingerprint are relative to it)


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
        if key in ("lens", "method", "align"):
            _typed(path, where, key, value, str)
        elif key == "blur_span_px":
            _typed(path, where, key, value, (int, float))
            if not value > 0:
                raise InputError(f"{path}: blur_span_px{where} must be > 0, got {value!r}")
            value = float(value)
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


# ---------------------------------------------------------------------- planning
def safe_name(text: str) -> str:
    """A file-name component from input names: no separators, no leading dots."""
    cleaned = re.sub(r"[^A-Za-z0-9._+-]+", "_", text).lstrip(".")
    return cleaned or "_"


def output_path(output_dir: Path, template: str, *, stack: str, parent: str) -> Path:
    """The output file of a stack; always inside ``output_dir``.

    Names derived from inputs pass through :func:`safe_name`; the result is
    checked again after resolving (no ``..``, absolute or symlink escapes).
    """
    rendered = template.format(stack=safe_name(stack), parent=safe_name(parent))
    relative = Path(rendered)
    if relative.is_absolute() or ".." in relative.parts:
        raise InputError(f"output name {rendered!r} must stay inside {output_dir}")
    target = output_dir / relative
    root = output_dir.resolve()
    if not target.resolve().is_relative_to(root):
        raise InputError(
            f"output name {rendered!r} resolves to {target.resolve()}, outside "
            f"the output directory {root}"
        )
    return target


def _display(path: Path, base: Path) -> str:
    try:
        return path.resolve().relative_to(base).as_posix()
    except ValueError:
        return path.resolve().as_posix()


def _visible_files(directory: Path) -> list[Path]:
    return sorted(
        (p for p in directory.iterdir() if p.is_file() and not p.name.startswith(".")),
        key=natural_key,
    )


def plan_stacks(workflow: Workflow) -> list[PlannedStack]:
    """Expand the inputs into stacks, with their outputs and options.

    Raises
    ------
    InputError
        An input glob that matches nothing, files that do not fit ``group_by``,
        and two stacks that would write the same output.
    """
    base = workflow.path.parent
    planned: list[PlannedStack] = []
    for index, spec in enumerate(workflow.inputs):
        where = f"{workflow.path}: [[inputs]] #{index + 1}"
        merged = {**workflow.options, **spec.options}
        options = StackOptions(
            lens=merged.get("lens"),
            method=merged.get("method", "wiener"),
            align=merged.get("align", "estimate"),
            encoding=workflow.encoding,
            blur_span_px=merged.get("blur_span_px"),
            tile_px=merged.get("tile_px", 1024),
            align_max_side_px=merged.get("align_max_side_px", 768),
        )
        if spec.directories is not None:
            pattern = str(base / spec.directories)
            found = sorted(
                (Path(p) for p in glob.glob(pattern) if Path(p).is_dir()), key=natural_key
            )
            if not found:
                raise InputError(
                    f"{where}: directories = {spec.directories!r} matches no "
                    f"directory (looked for {pattern})"
                )
            for directory in found:
                if spec.frames is not None:
                    paths = (str(directory / spec.frames),)
                    watch = tuple(
                        sorted(
                            (Path(p) for p in glob.glob(paths[0]) if Path(p).is_file()),
                            key=natural_key,
                        )
                    )
                else:
                    paths, watch = (str(directory),), tuple(_visible_files(directory))
                planned.append(
                    PlannedStack(
                        _display(directory, base),
                        paths,
                        output_path(
                            workflow.output_dir,
                            workflow.name_template,
                            stack=directory.resolve().name,
                            parent=directory.resolve().parent.name,
                        ),
                        options,
                        watch,
                        directory,
                    )
                )
        else:
            planned.extend(_plan_file_groups(workflow, spec, options, where))
    _check_unique(workflow, planned)
    return planned


def _plan_file_groups(
    workflow: Workflow, spec: InputSpec, options: StackOptions, where: str
) -> list[PlannedStack]:
    base = workflow.path.parent
    pattern = str(base / spec.files)
    files = [Path(p) for p in glob.glob(pattern, recursive=True) if Path(p).is_file()]
    files = [p for p in files if p.suffix.lower() in IMAGE_EXTENSIONS]
    if not files:
        raise InputError(
            f"{where}: files = {spec.files!r} matches no image files (looked for {pattern})"
        )
    groups: dict[tuple[Path, str], list[Path]] = {}
    regex = None if spec.group_by == "directory" else re.compile(spec.group_by)
    for file in files:
        if regex is None:
            name = file.resolve().parent.name
        else:
            match = regex.search(file.name)
            if match is None or not match.group("stack"):
                raise InputError(
                    f"{where}: {file.name} does not match group_by = "
                    f"{spec.group_by!r}; change the regex or the files glob"
                )
            name = match.group("stack")
        groups.setdefault((file.resolve().parent, name), []).append(file)
    planned = []
    for (folder, name), members in sorted(
        groups.items(), key=lambda kv: natural_key(f"{kv[0][0]}/{kv[0][1]}")
    ):
        members = sorted(members, key=natural_key)
        ident = _display(folder, base) if regex is None else f"{_display(folder, base)}#{name}"
        planned.append(
            PlannedStack(
                ident,
                tuple(str(m) for m in members),
                output_path(
                    workflow.output_dir,
                    workflow.name_template,
                    stack=name,
                    parent=folder.parent.name if regex is None else folder.name,
                ),
                options,
                tuple(members),
                folder,
            )
        )
    return planned


def _check_unique(workflow: Workflow, planned: Sequence[PlannedStack]) -> None:
    seen_ids: dict[str, PlannedStack] = {}
    seen_out: dict[Path, PlannedStack] = {}
    for stack in planned:
        if stack.id in seen_ids:
            raise InputError(
                f"{workflow.path}: stack {stack.id} is matched by two [[inputs]]; "
                "make the globs disjoint"
            )
        other = seen_out.get(stack.output.resolve())
        if other is not None:
            raise InputError(
                f"{workflow.path}: stacks {other.id} and {stack.id} would both write "
                f'{stack.output}; make names unique, e.g. name = "{{parent}}-{{stack}}'
                f'{Path(workflow.name_template).suffix}" in [output]'
            )
        seen_ids[stack.id] = stack
        seen_out[stack.output.resolve()] = stack


# ---------------------------------------------------------------------- fingerprints
def fingerprint(stack: PlannedStack, file_sha256: Callable[[Path], str]) -> str:
    """SHA-256 over the stack's input contents, its options, output name and flexdof version.

    The files are those the inputs name (every file of a stack directory,
    including ``stack.toml``), those the loaded stack refers to, and the lens
    profile, each by content (``file_sha256``), with names relative to the
    stack's folder. A stack that cannot be loaded still has a fingerprint (of
    what is there), so it is retried when its files change.
    """
    files = set(stack.watch)
    try:
        loaded = load_stack(list(stack.paths))
    except InputError:
        loaded = None
    if loaded is not None:
        files.update(loaded.files)
        if loaded.sweep is not None:
            files.add(loaded.sweep.file)
        if stack.options.lens is None and loaded.lens_profile is not None:
            files.add(Path(loaded.lens_profile.source))
    if stack.options.lens is not None:
        try:
            files.add(resolve_lens_path(stack.options.lens, base_dir=stack.base))
        except InputError:
            pass  # the task reports it as the stack's error; the name is in the options
    options = dataclasses.asdict(stack.options)
    options.pop("save_kernel")
    contents = sorted(
        (_display(f, stack.base.resolve()), file_sha256(f)) for f in files if f.is_file()
    )
    payload = {
        "flexdof": __version__,
        "options": options,
        "output": stack.output.name,
        "files": contents,
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode("utf-8")).hexdigest()


# ---------------------------------------------------------------------- runs
@dataclasses.dataclass
class RunSummary:
    """What a run did; ``failed`` lists (stack, error) of this run and of skipped
    stacks whose unchanged inputs failed before."""

    run_id: int
    planned: int
    skipped: list[str]
    done: list[str]
    failed: list[tuple[str, str]]
    seconds: float

    @property
    def ok(self) -> bool:
        return not self.failed


def _needs_run(record, fp: str, output: Path, retry_failed: bool) -> str | None:
    """Why a stack must be processed, or None when it is up to date."""
    if record is None:
        return "new"
    if record.fingerprint != fp:
        return "changed"
    if record.status == "done":
        sidecar = output.with_name(output.name + ".json")
        if output.is_file() and sidecar.is_file():
            return None
        return "output missing"
    if record.status == "failed" and record.error_kind == "input" and not retry_failed:
        return None
    return record.status  # interrupted, queued by a dead run, or a transient failure


def _remove_stale_temps(output: Path) -> None:
    """Temp files of atomic writes a killed run left behind (never complete outputs)."""
    for name in (output.name, output.name + ".json"):
        for temp in output.parent.glob(f".{glob.escape(name)}.*.tmp"):
            temp.unlink(missing_ok=True)


def run_workflow(
    workflow: Workflow,
    *,
    dry_run: bool = False,
    on_plan: Callable[[list[tuple[PlannedStack, str]], int], None] | None = None,
    on_result: Callable[[dict], None] | None = None,
    on_progress: OnProgress | None = None,
) -> RunSummary:
    """One incremental run: process new or changed stacks, record them in the ledger.

    Holds the output directory's :class:`~pipeline.ledger.RunLock` for the
    whole run (a second run is refused with
    :class:`~pipeline.ledger.LockedError`). ``on_plan(todo, skipped)`` is
    called once with the stacks to process and why.
    """
    start = time.perf_counter()
    planned = plan_stacks(workflow)  # validates everything before any work
    try:
        workflow.output_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(
            f"{workflow.path}: cannot create the output directory {workflow.output_dir} ({err})"
        ) from err
    with (
        RunLock(workflow.output_dir, f"workflow {workflow.path}"),
        Ledger(workflow.ledger_path) as ledger,
    ):
        fps = {s.id: fingerprint(s, ledger.file_sha256) for s in planned}
        todo, skipped, still_failed = [], [], []
        for stack in planned:
            record = ledger.get(stack.id)
            reason = _needs_run(record, fps[stack.id], stack.output, workflow.retry_failed)
            if reason is not None:
                todo.append((stack, reason))
            elif record.status == "failed":
                still_failed.append((stack.id, f"{record.error} (unchanged; not retried)"))
            else:
                skipped.append(stack.id)
        if on_plan is not None:
            on_plan(todo, len(planned) - len(todo))
        if dry_run:
            return RunSummary(0, len(planned), skipped, [], still_failed, 0.0)
        run_id = ledger.start_run(str(workflow.path), workflow.scheduler)
        jobs = []
        for stack, _ in todo:
            stack.output.parent.mkdir(parents=True, exist_ok=True)
            _remove_stale_temps(stack.output)
            ledger.queue(run_id, stack.id, list(stack.paths), str(stack.output), fps[stack.id])
            jobs.append(BatchJob(stack.id, stack.paths, str(stack.output), stack.options))
        done: list[str] = []
        failed: list[tuple[str, str]] = []

        def record(result: dict) -> None:
            ledger.record(run_id, result)
            if result["status"] == "done":
                done.append(result["key"])
            else:
                failed.append((result["key"], result["error"]))
            if on_result is not None:
                on_result(result)

        run_batch(
            jobs,
            scheduler=workflow.scheduler,
            concurrency=workflow.concurrency,
            threads_per_stack=workflow.threads_per_stack,
            on_result=record,
            on_progress=on_progress,
        )
        failed += still_failed
        ledger.finish_run(
            run_id, planned=len(planned), skipped=len(skipped), done=len(done), failed=len(failed)
        )
    return RunSummary(run_id, len(planned), skipped, done, failed, time.perf_counter() - start)


def run_every(
    interval_s: float,
    run_once: Callable[[], bool],
    *,
    runs: int | None = None,
    stop: threading.Event | None = None,
    on_error: Callable[[Exception], None] | None = None,
) -> int:
    """Call ``run_once`` every ``interval_s`` seconds (start to start); return the run count.

    A run that overruns its interval is followed at once by the next (missed
    ticks are skipped, never queued). Errors of one run (an invalid workflow
    edit, a refused lock) go to ``on_error`` and the loop goes on; the first
    run's errors propagate.
    """
    stop = stop or threading.Event()
    count = 0
    next_start = time.monotonic()
    while not stop.is_set() and (runs is None or count < runs):
        try:
            run_once()
        except FlexdofError as err:
            if count == 0 or on_error is None:
                raise
            on_error(err)
        count += 1
        if runs is not None and count >= runs:
            break
        next_start += interval_s
        next_start = max(next_start, time.monotonic())  # overran: start the next one now
        stop.wait(max(0.0, next_start - time.monotonic()))
    return count
