"""One CLI: the flag vocabulary, lazy imports, global flags, --json, quiet by default, and the
data a wheel must carry (shipped lens profiles and sample)."""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.cli import build_parser, main, subcommands
from pipeline.commands import _flags

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("numpy", "scipy", "cv2", "dask", "distributed", "skimage", "matplotlib", "rich")
# Commands that produce a result (and so take --json); tether is checked by its own tests.
RESULT_COMMANDS = (
    ("stack",),
    ("sweep",),
    ("dof",),
    ("simulate",),
    ("optics",),
    ("psf",),
    ("figures",),
    ("bench", "accuracy"),
    ("workflow", "run"),
    ("workflow", "status"),
    ("sample-path",),
)


def test_building_the_parser_imports_no_heavy_library():
    """`flexdof --help` must stay fast: no numpy, OpenCV, dask, scipy... at parse time."""
    code = (
        "import sys; from pipeline.cli import build_parser; build_parser(); "
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO
    )
    assert done.stdout.strip() == "", f"imported while building the parser: {done.stdout}"


def test_help_of_every_command_imports_no_heavy_library():
    code = (
        "import sys\nfrom pipeline.cli import build_parser\n"
        "import argparse\np = build_parser()\n"
        "for argv in (['stack', '-h'], ['sweep', '-h'], ['workflow', 'run', '-h'],"
        " ['tether', '-h'], ['bench', 'accuracy', '-h']):\n"
        "    try:\n        p.parse_args(argv)\n    except SystemExit:\n        pass\n"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO
    )
    assert done.stderr.strip() == ""


def test_mirrored_constants_agree_with_the_jobs():
    from pipeline.io.write import WRITE_ENCODINGS
    from pipeline.jobs.options import ALIGN_MODELS, ALIGN_MODES, METHODS, StackOptions

    assert set(_flags.CLI_METHODS) < set(METHODS)  # the sparse prior: API only
    assert _flags.ALIGN_MODES == ALIGN_MODES
    assert _flags.ALIGN_MODELS == ALIGN_MODELS
    assert build_parser().parse_args(["stack", "d", "-o", "x"]).align_model == (
        StackOptions().align_model
    )
    assert set(_flags.ENCODINGS) == set(WRITE_ENCODINGS[".tif"])


def test_every_option_has_help_and_one_vocabulary():
    parser = build_parser()
    banned = {"--out", "--near", "--far", "--exposure", "--depth-map", "--sweep-mm"}
    for path, sub in subcommands(parser):
        for action in sub._actions:
            if isinstance(action, argparse._SubParsersAction) or action.help == argparse.SUPPRESS:
                continue
            assert action.help, f"flexdof {' '.join(path)} {action.option_strings}: no help"
            shown = action.option_strings[:1]  # the canonical spelling comes first
            assert not banned & set(shown), (path, action.option_strings)
            if "-o" in action.option_strings:
                assert action.option_strings[:2] == ["-o", "--output"]


def test_json_on_every_command_with_a_result():
    commands = dict(subcommands(build_parser()))
    for path in RESULT_COMMANDS:
        flags = {s for a in commands[path]._actions for s in a.option_strings}
        assert "--json" in flags, path


def test_defaults_are_shown_in_help(capsys):
    with pytest.raises(SystemExit):
        main(["sweep", "--help"])
    text = " ".join(capsys.readouterr().out.split())  # undo the line wrapping
    assert "(default: wiener)" in text and "(default: 1024)" in text and "(default: inf)" in text
    assert "--near-mm" in text and "--near " not in text  # old spelling parses but is hidden
    assert "--linear" not in text and "(default: False)" not in text


def test_global_flags_anywhere():
    parser = build_parser()
    for argv in (
        ["-q", "optics"],
        ["optics", "-q"],
        ["optics", "--quiet"],
        ["workflow", "status", "w.toml", "-q"],
    ):
        args = parser.parse_args(argv)
        assert args.quiet and not args.verbose, argv
    args = parser.parse_args(["optics", "-v"])
    assert args.verbose and not args.quiet
    args = parser.parse_args(["optics"])
    assert not args.quiet and not args.verbose


def test_quiet_and_verbose_exclude_each_other(capsys):
    with pytest.raises(SystemExit) as info:
        main(["-q", "optics", "-v"])
    assert info.value.code == 2


def test_old_spellings_still_parse():
    parser = build_parser()
    args = parser.parse_args(
        ["sweep", "x.tif", "-o", "y.tif", "--lens", "L", "--near", "450", "--far", "900",
         "--exposure", "0.5", "--linear"]
    )
    assert (args.near_mm, args.far_mm, args.exposure_s, args.encoding) == (
        450.0, 900.0, 0.5, "linear16"
    )
    args = parser.parse_args(["figures", "--out", "d"])
    assert args.output == Path("d")
    args = parser.parse_args(["simulate", "s", "--lens", "L", "--sweep-mm", "450", "2000"])
    assert (args.near_mm, args.far_mm) == (450.0, 2000.0)
    args = parser.parse_args(["stack", "s", "-o", "x.tif", "--float"])
    assert args.encoding == "float32"


def test_logging_is_quiet_by_default_and_verbose_with_v():
    root = logging.getLogger()
    before = root.level
    try:
        cli.configure_logging(quiet=False, verbose=False)
        assert not logging.getLogger("pipeline.io.write").isEnabledFor(logging.INFO)
        assert logging.getLogger("pipeline").isEnabledFor(logging.WARNING)
        cli.configure_logging(quiet=False, verbose=True)
        assert logging.getLogger("pipeline.io.write").isEnabledFor(logging.INFO)
        cli.configure_logging(quiet=True, verbose=False)
        assert not logging.getLogger("pipeline").isEnabledFor(logging.WARNING)
    finally:
        root.setLevel(before)


def test_main_job_prints_no_normal_events_by_default(tmp_path):
    """Clipping counts and EXIF notes are for -v; the default run prints one result line."""
    sample = REPO / "stacks" / "motorcycle"
    out = tmp_path / "edof.tif"
    run = [sys.executable, "-m", "pipeline.cli", "stack", str(sample), "-o", str(out)]
    done = subprocess.run(run, capture_output=True, text=True, check=True, cwd=tmp_path)
    assert "INFO" not in done.stderr and "clipped" not in done.stderr, done.stderr
    assert done.stdout.startswith(f"wrote {out}")
    verbose = subprocess.run(
        [*run, "-v", "--json"], capture_output=True, text=True, check=True, cwd=tmp_path
    )
    assert "INFO" in verbose.stderr or "DEBUG" in verbose.stderr
    summary = json.loads(verbose.stdout)
    assert summary["output"] == str(out) and summary["frames"] == 8


def test_shipped_data_is_found_and_listed_in_the_wheel_mapping():
    from pipeline.io.profiles import available_lenses, shipped

    assert (shipped("sample") / "stack.toml").is_file()
    assert "fujinon-12.5mm-f1.4-sony-1-3in" in available_lenses()
    config = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    setuptools = config["tool"]["setuptools"]
    packages = set(setuptools["packages"])
    source = {
        ".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "pipeline").rglob("__init__.py")
    }
    assert source <= packages, f"add to [tool.setuptools] packages: {sorted(source - packages)}"
    mapped = setuptools["package-dir"]
    assert mapped["pipeline._data.lens_profiles"] == "lens_profiles"
    assert mapped["pipeline._data.motorcycle"] == "stacks/motorcycle"
    sample_files = {p.name for p in shipped("sample").iterdir()}
    patterns = setuptools["package-data"]["pipeline._data.motorcycle"]
    assert all(any(Path(n).match(p) for p in patterns) for n in sample_files), sample_files


def test_sample_path_command(capsys):
    assert main(["sample-path"]) == 0
    assert Path(capsys.readouterr().out.strip()) == (REPO / "stacks" / "motorcycle").resolve()
    assert main(["sample-path", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert "fujinon-12.5mm-f1.4-sony-1-3in" in data["lenses"]


def test_missing_matplotlib_is_one_line_with_the_install_command(monkeypatch, tmp_path, capsys):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "matplotlib" else real(name)
    )
    assert main(["figures", "-o", str(tmp_path / "f")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "pip install 'flexdof[plots]'" in err


def test_dof_range_touching_the_stack_end_is_clamped(tmp_path, capsys):
    """The sample's frames span about 450-2000 mm: 449 (0.2% nearer) is the end frame."""
    sample = REPO / "stacks" / "motorcycle"
    out = tmp_path / "dof.tif"
    argv = ["dof", str(sample), "-o", str(out), "--in-focus", "449:600", "--json"]
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out)["frames_used"] >= 1
    assert main(["dof", str(sample), "-o", str(out), "--in-focus", "100:300"]) == 2
    err = capsys.readouterr().err
    assert "--in-focus 100:300" in err and "focus range" in err and "outside=" not in err


def test_render_reports_progress_per_step():
    """`flexdof simulate` shows a bar fed by render(progress=...): one call per plan step."""
    import numpy as np

    from pipeline.core import optics, simulate
    from pipeline.core.lens import Lens
    from pipeline.core.motion import Profile
    from pipeline.core.scene import Camera, Scene

    lens = Lens(focal_length_mm=12.5, f_number=1.4, pixel_pitch_um=4.65, width_px=48, height_px=32)
    depth = np.where(np.arange(48)[None, :] < 24, 450.0, 2000.0) * np.ones((32, 1))
    scene = Scene.from_depth(np.random.default_rng(0).uniform(0, 1, (32, 48)), depth)
    ends = [optics.image_distance(12.5, 2000), optics.image_distance(12.5, 450)]
    sweep = Profile([0.0, 0.1], ends)
    calls = []
    simulate.render(scene, Camera(lens, sweep), progress=lambda d, t: calls.append((d, t)))
    assert calls and calls[-1][0] == calls[-1][1] and [d for d, _ in calls] == list(
        range(1, len(calls) + 1)
    )


@pytest.mark.parametrize("flag", ["--max-pixels", "--tile-px"])
def test_a_zero_limit_is_refused_not_replaced_by_the_default(tmp_path, capsys, flag):
    sample = REPO / "stacks" / "motorcycle"
    assert main(["stack", str(sample), "-o", str(tmp_path / "a.tif"), flag, "0"]) == 2
    name = flag.lstrip("-").replace("-", "_")
    assert f"{name} must be an integer >= 1" in capsys.readouterr().err
    assert not (tmp_path / "a.tif").exists()
