"""docs/formats.md stays true to the code that reads and writes each format.

* Every key the parsers accept (stack.toml, lens profiles, workflow files) and
  every key of a real result sidecar is documented in its section of the doc;
  every key in the doc's key tables is one the code knows.
* Every TOML example in the doc loads with the project's own loader (the
  ``<!-- check: KIND -->`` comment above it says which), with the files it
  refers to created in a temporary folder; every JSON example parses and uses
  only real sidecar keys.
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.lens import MECHANISMS, PSF_MODELS, SHUTTERS, Lens
from pipeline.io.profiles import _SCHEMA as LENS_SCHEMA
from pipeline.io.profiles import available_lenses, load_lens
from pipeline.io.stackfile import (
    _FRAME_KEYS,
    _SWEEP_KEYS,
    _SWEEP_PAIRS,
    KINDS,
    SWEEP_PROFILES,
    load_stack,
)
from pipeline.io.stackfile import _TOP_KEYS as STACK_TOP_KEYS
from pipeline.io.write import WRITE_ENCODINGS, write_image

# --- names under test (modules may move: rewrite only this block) ---------------------------
from pipeline.jobs.options import ALIGN_MODELS, ALIGN_MODES, METHODS, StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.scheduler import scheduler_context
from pipeline.workflow.ledger import LEDGER_NAME, LOCK_NAME
from pipeline.workflow.schema import (
    _INPUT_KEYS,
    _NAME_FIELDS,
    _OPTION_KEYS,
    _OUTPUT_KEYS,
    _RUN_KEYS,
    _SCHEDULE_KEYS,
    load_workflow,
)
from pipeline.workflow.schema import _TOP_KEYS as WORKFLOW_TOP_KEYS

# ---------------------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parents[1]
DOC = REPO / "docs" / "formats.md"
TEXT = DOC.read_text(encoding="utf-8")

STACK_KEYS = {*STACK_TOP_KEYS, *_FRAME_KEYS, *_SWEEP_KEYS}
LENS_KEYS = {key for table in LENS_SCHEMA.values() for key in table}
WORKFLOW_KEYS = {
    *WORKFLOW_TOP_KEYS,
    *_INPUT_KEYS,
    *_OPTION_KEYS,
    *_OUTPUT_KEYS,
    *_RUN_KEYS,
    *_SCHEDULE_KEYS,
}


def section(title_start: str) -> str:
    """The text of the ``## `` section whose title starts with ``title_start``."""
    parts = re.split(r"^## ", TEXT, flags=re.MULTILINE)
    found = [part for part in parts if part.startswith(title_start)]
    assert len(found) == 1, f"docs/formats.md needs one section '## {title_start}...'"
    return found[0]


STACK_DOC = section("`stack.toml`")
LENS_DOC = section("Lens profiles")
WORKFLOW_DOC = section("Workflow files")
SIDECAR_DOC = section("The result sidecar")
TETHER_DOC = section("Tethered capture outputs")


def mentioned(name: str, text: str) -> bool:
    """``name`` in backticks: `name`, `"name"` (a string value) or `owner.name`."""
    return bool(re.search(r'`(?:[\w-]+\.)?"?' + re.escape(name) + r'"?`', text))


def assert_documented(names, text: str, where: str) -> None:
    missing = sorted(name for name in names if not mentioned(name, text))
    assert not missing, f"not documented (in backticks) in the {where} section: {missing}"


def table_keys(text: str) -> set[str]:
    """Backticked names in the first column of the tables whose header starts ``| key |``."""
    keys: set[str] = set()
    in_key_table = False
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped.startswith("|"):
            in_key_table = False
            continue
        cells = [cell.strip() for cell in stripped.strip("|").split("|")]
        if cells[0] == "key":
            in_key_table = True
        elif in_key_table and not set(cells[0]) <= set("-: "):
            keys.update(re.findall(r"`([^`]+)`", cells[0]))
    return keys


# --- keys: code -> doc and doc -> code -------------------------------------------------------


def test_stack_toml_keys_documented():
    assert_documented(STACK_KEYS, STACK_DOC, "stack.toml")
    assert_documented([key for pair in _SWEEP_PAIRS for key in pair], STACK_DOC, "stack.toml")
    assert_documented(KINDS, STACK_DOC, "stack.toml")
    assert all(f'"{profile}"' in STACK_DOC for profile in SWEEP_PROFILES)
    assert table_keys(STACK_DOC) <= STACK_KEYS


def test_lens_profile_keys_documented():
    assert_documented(LENS_KEYS, LENS_DOC, "lens profile")
    assert_documented([f"[{table}]" for table in LENS_SCHEMA if table], LENS_DOC, "lens profile")
    fields = Lens.__dataclass_fields__
    assert_documented(fields, LENS_DOC, "lens profile")
    mapped = {field for table in LENS_SCHEMA.values() for field, _required in table.values()}
    assert set(fields) - mapped == {"source"}, "a Lens field without a TOML key: document it"
    for values in (SHUTTERS, PSF_MODELS, MECHANISMS):
        assert all(f'"{value}"' in LENS_DOC for value in values)
    assert_documented(available_lenses(), LENS_DOC, "lens profile")
    required = {key for table in LENS_SCHEMA.values() for key, (_f, req) in table.items() if req}
    rows = {row.split("|")[1].strip(" `"): row for row in LENS_DOC.splitlines() if "|" in row}
    for key in LENS_KEYS:
        assert ("| yes |" in rows[key]) == (key in required), f"lens key {key}: required?"
    assert table_keys(LENS_DOC) <= LENS_KEYS


def test_workflow_keys_documented():
    assert_documented(WORKFLOW_KEYS, WORKFLOW_DOC, "workflow")
    assert_documented([f"{{{name}}}" for name in _NAME_FIELDS], WORKFLOW_DOC, "workflow")
    assert_documented([*METHODS, *ALIGN_MODES, *ALIGN_MODELS], WORKFLOW_DOC, "workflow")
    encodings = {enc for allowed in WRITE_ENCODINGS.values() for enc in allowed}
    assert_documented([*WRITE_ENCODINGS, *encodings], WORKFLOW_DOC, "workflow")
    assert_documented([LEDGER_NAME, LOCK_NAME], WORKFLOW_DOC, "workflow")
    assert table_keys(WORKFLOW_DOC) <= WORKFLOW_KEYS


def test_license_is_mit():
    licence = (REPO / "LICENSE").read_text(encoding="utf-8")
    assert licence.startswith("MIT License")
    assert "Copyright (c) 2026 the flexdof authors" in licence
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    assert pyproject["project"]["license"] == "MIT"


# --- the result sidecar: keys of real runs ---------------------------------------------------

LENS_TOML = """\
name = "docs test lens"
focal_length_mm = 12.5
f_number = 1.4

[sensor]
pixel_pitch_um = 50.0
width_px = 48
height_px = 40
"""


def _scene(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = rng.random((40, 48)).astype(np.float32)
    return 0.2 + 0.6 * (image + np.roll(image, 1, 0) + np.roll(image, 1, 1)) / 3


def _keys(obj, prefix: str = "") -> set[str]:
    """Every dict key in ``obj`` (recursing into dicts and lists of dicts)."""
    keys: set[str] = set()
    if isinstance(obj, dict):
        for key, value in obj.items():
            keys.add(key)
            keys |= _keys(value)
    elif isinstance(obj, list):
        for item in obj:
            keys |= _keys(item)
    return keys


@pytest.fixture(scope="module")
def sidecar_keys(tmp_path_factory) -> set[str]:
    """Keys of the sidecars of a small focal stack and a small sweep capture."""
    base = tmp_path_factory.mktemp("sidecars")
    stack = base / "stack"
    stack.mkdir()
    (stack / "lens.toml").write_text(LENS_TOML, encoding="utf-8")
    lines = ['lens = "lens.toml"']
    for i, v in enumerate((12.5, 12.675, 12.85)):
        write_image(stack / f"f{i}.tif", _scene(i), encoding="float32")
        lines += ["[[frames]]", f'file = "f{i}.tif"', f"image_distance_mm = {v}"]
    (stack / "stack.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    sweep = base / "sweep"
    sweep.mkdir()
    (sweep / "lens.toml").write_text(LENS_TOML, encoding="utf-8")
    write_image(sweep / "capture.tif", _scene(), encoding="float32")
    (sweep / "stack.toml").write_text(
        'lens = "lens.toml"\nkind = "sweep"\n[sweep]\nfile = "capture.tif"\n'
        "start_focus_distance_mm = inf\nend_focus_distance_mm = 300.0\nexposure_s = 0.1\n",
        encoding="utf-8",
    )
    keys: set[str] = set()
    with scheduler_context(threads=1):
        for run, (directory, options) in enumerate((
            (stack, StackOptions(align="analytic", save_kernel=base / "kernel.tif",
                                 frame_guard=True)),
            (stack, StackOptions(align="analytic")),  # the default's frame_range
            (stack, StackOptions(align="analytic", method="multiframe")),
            (sweep, StackOptions()),
        )):
            output = base / f"{directory.name}{run}.tif"
            process_stack(directory, output, options)
            keys |= _keys(json.loads(output.with_name(output.name + ".json").read_text()))
    return keys


def test_sidecar_keys_documented(sidecar_keys):
    assert_documented(sidecar_keys, SIDECAR_DOC, "result sidecar")
    documented = {key.split(".")[-1] for key in table_keys(SIDECAR_DOC)}
    assert documented <= sidecar_keys


def test_json_examples_use_real_keys(sidecar_keys):
    blocks = re.findall(r"```json\n(.*?)```", TEXT, flags=re.DOTALL)
    assert blocks
    for block in blocks:
        example = json.loads(block)
        assert _keys(example) <= sidecar_keys, _keys(example) - sidecar_keys


# --- TOML examples load with the project's loaders -------------------------------------------

EXAMPLES = re.findall(r"(<!-- check: (\w+) -->\s*\n)?[ \t]*```toml\n(.*?)```", TEXT, re.DOTALL)


def test_every_toml_example_is_checked():
    assert EXAMPLES
    unchecked = [body[:60] for marker, _kind, body in EXAMPLES if not marker]
    assert not unchecked, f"```toml blocks without <!-- check: KIND --> above them: {unchecked}"


def _dedent(body: str) -> str:
    lines = body.splitlines()
    indent = min(len(line) - len(line.lstrip()) for line in lines if line.strip())
    return "\n".join(line[indent:] for line in lines) + "\n"


def _provide_lens(value: str | None, base: Path) -> None:
    """A lens path an example refers to: a copy of a shipped profile there."""
    if value is None or value in available_lenses():
        return
    target = base / value
    target.parent.mkdir(parents=True, exist_ok=True)
    source = load_lens(available_lenses()[0]).source
    target.write_text(Path(source).read_text(encoding="utf-8"), encoding="utf-8")


def _provide_image(name: str, base: Path) -> None:
    path = base / name
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() in WRITE_ENCODINGS:
        write_image(path, np.full((8, 8), 0.5, np.float32))
    else:  # RAW: load_stack checks existence and extension, it does not decode
        path.write_bytes(b"")


@pytest.mark.parametrize(
    "kind,body",
    [(kind, _dedent(body)) for _marker, kind, body in EXAMPLES],
    ids=[f"{i}-{kind}" for i, (_m, kind, _b) in enumerate(EXAMPLES)],
)
def test_toml_example_loads(kind, body, tmp_path):
    data = tomllib.loads(body)
    if kind == "toml":  # a file no loader reads (drives.toml): valid TOML is all
        return
    if kind == "stack":
        _provide_lens(data.get("lens"), tmp_path)
        files = [frame["file"] for frame in data.get("frames", [])]
        files += [data["sweep"]["file"]] if "sweep" in data else []
        for name in files:
            _provide_image(name, tmp_path)
        (tmp_path / "stack.toml").write_text(body, encoding="utf-8")
        stack = load_stack(tmp_path / "stack.toml")
        assert stack.kind == data.get("kind", "focal-stack")
        assert len(stack.frames) == max(len(files) - ("sweep" in data), 1)
    elif kind == "lens":
        (tmp_path / "example.toml").write_text(body, encoding="utf-8")
        lens = load_lens(tmp_path / "example.toml")
        assert lens.focal_length_mm == data["focal_length_mm"]
    elif kind == "workflow":
        _provide_lens(data.get("options", {}).get("lens"), tmp_path)
        for spec in data["inputs"]:
            _provide_lens(spec.get("options", {}).get("lens"), tmp_path)
        (tmp_path / "workflow.toml").write_text(body, encoding="utf-8")
        workflow = load_workflow(tmp_path / "workflow.toml")
        assert len(workflow.inputs) == len(data["inputs"])
    else:
        pytest.fail(f"unknown check kind {kind!r}: use stack, lens, workflow or toml")
