"""The stacks a workflow names (stack folders or frame files grouped into stacks),
their output paths, and their input fingerprints.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import json
import re
from collections.abc import Callable, Sequence
from pathlib import Path

from pipeline import __version__
from pipeline.errors import InputError
from pipeline.io.probe import IMAGE_EXTENSIONS
from pipeline.io.profiles import resolve_lens_path
from pipeline.io.stackfile import is_flexdof_result, load_stack, natural_key
from pipeline.jobs.options import StackOptions
from pipeline.workflow.schema import InputSpec, Workflow


@dataclasses.dataclass(frozen=True)
class PlannedStack:
    """One stack found by a workflow's inputs."""

    id: str  # ledger key: the stack's directory (or group) relative to the workflow file
    paths: tuple[str, ...]  # what load_stack takes
    output: Path
    options: StackOptions
    watch: tuple[Path, ...]  # files whose content defines the stack (fingerprint)
    base: Path  # the stack's folder (file names in the fingerprint are relative to it)


class NoInputsYet(InputError):
    """An input glob matches nothing (yet): for a scheduled workflow, nothing to do."""


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


def _visible_files(directory: Path, outputs: Path | None = None) -> list[Path]:
    return sorted(
        (
            p
            for p in directory.iterdir()
            if p.is_file()
            and not p.name.startswith(".")
            and (outputs is None or not _inside(p, outputs))
        ),
        key=natural_key,
    )


def _inside(path: Path, folder: Path | None) -> bool:
    return folder is not None and path.resolve().is_relative_to(folder)


def _excluded_outputs(pattern: str, outputs: Path) -> Path | None:
    """The output directory when it lies below the glob's fixed part (so the glob can reach
    into it), else None (an output directory at or above the inputs excludes nothing)."""
    fixed = []
    for part in Path(pattern).parts:
        if any(ch in part for ch in "*?["):
            break
        fixed.append(part)
    root = Path(*fixed).resolve() if fixed else Path.cwd()
    return outputs if outputs != root and outputs.is_relative_to(root) else None


def plan_stacks(
    workflow: Workflow, *, empty_ok: bool = False, on_empty: Callable[[str], None] | None = None
) -> list[PlannedStack]:
    """Expand the inputs into stacks, with their outputs and options.

    Everything inside the output directory (the workflow's own results, the
    ledger) is left out of the inputs, so an output folder under an input glob
    is never processed as a stack. With ``empty_ok`` (scheduled runs), an input
    that matches nothing yet is reported to ``on_empty`` and skipped.

    Raises
    ------
    NoInputsYet
        An input glob that matches nothing (without ``empty_ok``).
    InputError
        Files that do not fit ``group_by``, and two stacks that would write the
        same output.
    """
    base = workflow.path.parent
    outputs = workflow.output_dir.resolve()
    planned: list[PlannedStack] = []
    for index, spec in enumerate(workflow.inputs):
        where = f"{workflow.path}: [[inputs]] #{index + 1}"
        merged = {**workflow.options, **spec.options}
        # every options key of a workflow file is the StackOptions field of that name
        # (pipeline.workflow.schema): the job's defaults fill the rest
        options = StackOptions(encoding=workflow.encoding, **merged)
        if spec.directories is not None:
            pattern = str(base / spec.directories)
            excluded = _excluded_outputs(pattern, outputs)
            found = sorted(
                (
                    Path(p)
                    for p in glob.glob(pattern)
                    if Path(p).is_dir() and not _inside(Path(p), excluded)
                ),
                key=natural_key,
            )
            if not found:
                message = (
                    f"{where}: directories = {spec.directories!r} matches no "
                    f"directory (looked for {pattern})"
                )
                if not empty_ok:
                    raise NoInputsYet(message)
                if on_empty is not None:
                    on_empty(message)
                continue
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
                    paths, watch = (str(directory),), tuple(_visible_files(directory, excluded))
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
            try:
                planned.extend(_plan_file_groups(workflow, spec, options, where, outputs))
            except NoInputsYet as err:
                if not empty_ok:
                    raise
                if on_empty is not None:
                    on_empty(str(err))
    _check_unique(workflow, planned)
    return planned


def _plan_file_groups(
    workflow: Workflow, spec: InputSpec, options: StackOptions, where: str, outputs: Path
) -> list[PlannedStack]:
    base = workflow.path.parent
    pattern = str(base / spec.files)
    files = [Path(p) for p in glob.glob(pattern, recursive=True) if Path(p).is_file()]
    excluded = _excluded_outputs(pattern, outputs)
    files = [
        p
        for p in files
        if p.suffix.lower() in IMAGE_EXTENSIONS
        and not _inside(p, excluded)
        and not is_flexdof_result(p)  # outputs written beside the inputs
    ]
    if not files:
        raise NoInputsYet(
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
    options.pop("max_pixels")  # a safety limit: it never changes an output
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
