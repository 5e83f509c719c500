"""Workflow planning and runs, piece by piece, with hand-made inputs (issue 11, mutation
kills of ``workflow/plan.py`` and ``workflow/run.py``): the loop of ``--every`` on a fake
clock, why a stack is (not) processed, which temporaries are stale, names, globs and the
fingerprint's invariances. No stack is processed, so all of it runs in about a second.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
from test_batch import make_synthetic_stack

from pipeline.errors import FlexdofError, InputError
from pipeline.io.write import temp_prefix
from pipeline.workflow import plan as wplan
from pipeline.workflow import run as wrun
from pipeline.workflow.schema import load_workflow


# ---------------------------------------------------------------------- run_every
class FakeClock:
    """time.monotonic and an Event's wait on one fake time line."""

    def __init__(self):
        self.now = 100.0
        self.starts: list[float] = []
        self.waits: list[float] = []
        self.stopped = False

    def monotonic(self) -> float:
        return self.now

    def is_set(self) -> bool:
        return self.stopped

    def wait(self, seconds: float) -> bool:
        self.waits.append(seconds)
        self.now += seconds
        return self.stopped


@pytest.fixture
def clock(monkeypatch) -> FakeClock:
    fake = FakeClock()
    monkeypatch.setattr(wrun.time, "monotonic", fake.monotonic)
    return fake


def _job(clock: FakeClock, durations):
    durations = iter(durations)

    def run_once():
        clock.starts.append(clock.now)
        clock.now += next(durations)
        return True

    return run_once


def test_every_starts_runs_an_interval_apart_start_to_start(clock):
    count = wrun.run_every(10.0, _job(clock, [3.0, 1.0, 9.5, 0.0]), runs=4, stop=clock)
    assert count == 4
    assert clock.starts == [100.0, 110.0, 120.0, 130.0]
    assert clock.waits == [7.0, 9.0, 0.5]  # none after the last run


def test_every_after_an_overrun_starts_at_once_and_drops_the_missed_ticks(clock):
    wrun.run_every(10.0, _job(clock, [25.0, 2.0, 2.0]), runs=3, stop=clock)
    # 25 s overran two ticks (110, 120): the next run starts at 125, then 135
    assert clock.starts == [100.0, 125.0, 135.0]
    assert clock.waits == [0.0, 8.0]


def test_every_stops_when_told(clock):
    def run_once():
        clock.starts.append(clock.now)
        assert len(clock.starts) <= 2, "ran on after the stop"
        clock.stopped = len(clock.starts) == 2
        return True

    assert wrun.run_every(1.0, run_once, stop=clock) == 2
    clock.stopped = True
    assert wrun.run_every(1.0, run_once, stop=clock) == 0


def test_every_reports_later_errors_and_goes_on_but_raises_the_first(clock):
    calls = []

    def failing_second():
        calls.append(clock.now)
        if len(calls) == 2:
            raise InputError("an invalid edit")
        return True

    errors = []
    assert wrun.run_every(5.0, failing_second, runs=3, stop=clock, on_error=errors.append) == 3
    assert [str(e) for e in errors] == ["an invalid edit"] and len(calls) == 3

    def failing_first():
        raise InputError("bad from the start")

    with pytest.raises(InputError, match="bad from the start"):
        wrun.run_every(5.0, failing_first, runs=3, stop=clock, on_error=errors.append)
    calls.clear()
    with pytest.raises(InputError, match="invalid edit"):  # no on_error: it propagates
        wrun.run_every(5.0, failing_second, runs=3, stop=clock)

    def crash():
        raise RuntimeError("a bug")

    with pytest.raises(RuntimeError):  # not a FlexdofError: never swallowed
        wrun.run_every(5.0, crash, runs=3, stop=clock, on_error=errors.append)
    assert issubclass(InputError, FlexdofError)


# ---------------------------------------------------------------------- _needs_run
def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _record(**kw):
    base = dict(fingerprint="fp", status="done", error_kind=None, output_sha256=None)
    return SimpleNamespace(**{**base, **kw})


def test_why_a_stack_is_processed_or_not(tmp_path):
    out = tmp_path / "s.tif"
    out.write_bytes(b"image")
    (tmp_path / "s.tif.json").write_text("{}")
    need = wrun._needs_run
    assert need(None, "fp", out, False, _sha) == "new"
    assert need(_record(fingerprint="old"), "fp", out, False, _sha) == "changed"
    assert need(_record(output_sha256=_sha(out)), "fp", out, False, _sha) is None
    assert need(_record(output_sha256=""), "fp", out, False, _sha) is None  # no hash kept
    for other in ("0" * 64, "f" * 64):  # below and above the real hash
        changed = _record(output_sha256=other)
        assert need(changed, "fp", out, False, _sha) == "output changed since it was written"
    bad_input = _record(status="failed", error_kind="input")
    assert need(bad_input, "fp", out, False, _sha) is None  # unchanged bad input: not again
    assert need(bad_input, "fp", out, True, _sha) == "failed"  # retry_failed
    for kind in ("transient", "internal", None):
        assert need(_record(status="failed", error_kind=kind), "fp", out, False, _sha) == "failed"
    for status in ("running", "queued", "interrupted"):
        assert need(_record(status=status), "fp", out, False, _sha) == status


# ---------------------------------------------------------------------- stale temporaries
def test_only_the_outputs_own_temporaries_are_removed(tmp_path):
    out = tmp_path / "a[1].tif"  # glob characters in the name are literal
    sidecar = tmp_path / "a[1].tif.json"
    ours = [tmp_path / (temp_prefix(out) + "123.tmp"), tmp_path / (temp_prefix(sidecar) + "9.tmp")]
    keep = [
        tmp_path / (temp_prefix(tmp_path / "a1.tif") + "5.tmp"),  # what a[1] would match
        tmp_path / (temp_prefix(out) + "123.part"),  # not a temporary
        out,
        sidecar,
        tmp_path / "b.tif.tmp",
    ]
    for p in ours + keep:
        p.write_text("x")
    wrun._remove_stale_temps(out)
    assert [p.exists() for p in ours] == [False, False]
    assert all(p.exists() for p in keep)


def test_run_summary_is_ok_without_failures():
    assert wrun.RunSummary(1, 2, [], ["a", "b"], [], 0.1).ok
    assert not wrun.RunSummary(1, 2, [], ["a"], [("b", "bad")], 0.1).ok


# ---------------------------------------------------------------------- names and globs
@pytest.mark.parametrize(
    ("text", "name"),
    [
        ("pcb_7", "pcb_7"),
        ("a b/c", "a_b_c"),
        ("..hidden", "hidden"),
        ("...", "_"),
        ("", "_"),
        ("x.y+z-1", "x.y+z-1"),
        ("é:*?", "_"),
        ("a..b", "a..b"),
    ],
)
def test_safe_name(text, name):
    assert wplan.safe_name(text) == name


def test_output_path_fills_the_template_and_stays_inside(tmp_path):
    got = wplan.output_path(tmp_path, "{parent}-{stack}.tif", stack="s 1", parent="../p")
    assert got == tmp_path / "_p-s_1.tif"
    assert wplan.output_path(tmp_path, "sub/{stack}.png", stack="a", parent="b") == (
        tmp_path / "sub" / "a.png"
    )
    for template in ("../{stack}.tif", "/abs/{stack}.tif", "sub/../../{stack}.tif"):
        with pytest.raises(InputError, match="inside"):
            wplan.output_path(tmp_path, template, stack="a", parent="b")


def test_outputs_are_excluded_only_below_the_globs_fixed_part(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    inputs = tmp_path / "in"
    below = (inputs / "out").resolve()
    assert wplan._excluded_outputs(str(inputs / "*" / "*.png"), below) == below
    assert wplan._excluded_outputs(str(inputs / "*"), inputs.resolve()) is None  # the root
    assert wplan._excluded_outputs(str(inputs / "*"), (tmp_path / "elsewhere").resolve()) is None
    assert wplan._excluded_outputs(str(inputs / "a?" / "*"), below) == below
    assert wplan._excluded_outputs(str(inputs / "[ab]" / "*"), below) == below
    # a pattern with no fixed part is relative to the working directory
    assert wplan._excluded_outputs("*/x.png", (tmp_path / "o").resolve()) == (tmp_path / "o")


def test_visible_files_in_natural_order_without_hidden_or_outputs(tmp_path):
    for name in ("f10.png", "f2.png", "F1.png", ".hidden.png", "stack.toml"):
        (tmp_path / name).write_text("x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "r.tif").write_text("x")
    names = [p.name for p in wplan._visible_files(tmp_path)]
    assert names == ["F1.png", "f2.png", "f10.png", "stack.toml"]
    out = (tmp_path / "f10.png").resolve()
    assert "f10.png" not in [p.name for p in wplan._visible_files(tmp_path, out)]


# ---------------------------------------------------------------------- plans and fingerprints
def _tree(root: Path) -> Path:
    for name, seed in (("s2", 1), ("s10", 2)):
        make_synthetic_stack(root / "stacks" / name, seed=seed, frames=2, shape=(24, 32))
    return root


def _flow(root: Path, extra: str = "", inputs_extra: str = "") -> Path:
    path = root / "flow.toml"
    path.write_text(
        '[[inputs]]\ndirectories = "stacks/*"\n' + inputs_extra
        + '[options]\nblur_span_px = 5.0\nmethod = "rl"\n'
        + '[output]\ndirectory = "out"\n' + extra
    )
    return path


def test_every_workflow_option_is_a_job_option_of_that_name():
    """plan_stacks passes the options table to StackOptions by name."""
    import dataclasses

    from pipeline.jobs.options import StackOptions
    from pipeline.workflow import schema

    assert set(schema._OPTION_KEYS) <= {f.name for f in dataclasses.fields(StackOptions)}


def test_plan_order_options_and_defaults(tmp_path):
    root = _tree(tmp_path)
    stacks = wplan.plan_stacks(load_workflow(_flow(root)))
    assert [s.id for s in stacks] == ["stacks/s2", "stacks/s10"]  # natural order
    first = stacks[0]
    assert first.options.method == "rl" and first.options.blur_span_px == 5.0
    assert (first.options.align, first.options.tile_px, first.options.align_max_side_px) == (
        "estimate", 1024, 768)
    assert first.output.name == "s2.tif" and first.base == root / "stacks" / "s2"
    assert [p.name for p in first.watch] == ["frame_00.png", "frame_01.png"]
    assert first.paths == (str(root / "stacks" / "s2"),)
    overridden = _flow(root, inputs_extra='options = { method = "wiener", tile_px = 256 }\n')
    stacks = wplan.plan_stacks(load_workflow(overridden))
    assert stacks[0].options.method == "wiener" and stacks[0].options.tile_px == 256
    assert stacks[0].options.blur_span_px == 5.0  # the rest from [options]
    assert (first.options.frame_guard, first.options.frame_range) == (False, True)
    guarded = _flow(root, inputs_extra="options = { frame_guard = true, frame_range = false }\n")
    options = wplan.plan_stacks(load_workflow(guarded))[0].options
    assert (options.frame_guard, options.frame_range) == (True, False)  # were ignored
    assert first.options.white is None
    white = _flow(root, inputs_extra="options = { white = 4095 }\n")
    assert wplan.plan_stacks(load_workflow(white))[0].options.white == 4095.0
    assert first.options.align_model == "similarity"
    tilted = _flow(root, inputs_extra='options = { align_model = "keystone" }\n')
    assert wplan.plan_stacks(load_workflow(tilted))[0].options.align_model == "keystone"
    models = r"auto, similarity, breathing, keystone"
    with pytest.raises(InputError, match=rf"align_model .*must be one of {models}"):
        load_workflow(_flow(root, inputs_extra='options = { align_model = "perspective" }\n'))


def test_fingerprint_follows_contents_options_and_name_not_location(tmp_path):
    root = _tree(tmp_path / "one")
    stacks = wplan.plan_stacks(load_workflow(_flow(root)))
    fp = {s.id: wplan.fingerprint(s, _sha) for s in stacks}
    assert len(set(fp.values())) == 2
    moved = tmp_path / "two"
    shutil.copytree(root, moved)
    again = {s.id: wplan.fingerprint(s, _sha) for s in wplan.plan_stacks(load_workflow(
        _flow(moved)))}
    assert again == fp  # names relative to the stack's folder: a moved tree is unchanged
    s = stacks[0]
    assert wplan.fingerprint(dataclasses.replace(
        s, options=dataclasses.replace(s.options, save_kernel=Path("k.npy"), max_pixels=5)),
        _sha) == fp[s.id]  # neither changes an output
    assert wplan.fingerprint(dataclasses.replace(
        s, options=dataclasses.replace(s.options, tile_px=512)), _sha) != fp[s.id]
    assert wplan.fingerprint(dataclasses.replace(s, output=s.output.with_name("x.tif")),
                             _sha) != fp[s.id]
    frame = sorted(s.base.glob("*.png"))[0]
    os.utime(frame, (1, 1))  # a touch is not a change
    assert wplan.fingerprint(s, _sha) == fp[s.id]
    frame.write_bytes(frame.read_bytes() + b"\0")
    assert wplan.fingerprint(s, _sha) != fp[s.id]


def test_two_inputs_matching_one_stack_or_one_output_are_refused(tmp_path):
    root = _tree(tmp_path)
    path = root / "flow.toml"
    path.write_text(
        '[[inputs]]\ndirectories = "stacks/*"\n[[inputs]]\ndirectories = "stacks/s2"\n'
        '[output]\ndirectory = "out"\n'
    )
    with pytest.raises(InputError, match="matched by two"):
        wplan.plan_stacks(load_workflow(path))
    make_synthetic_stack(root / "more" / "s2", seed=3, frames=2, shape=(24, 32))
    path.write_text(
        '[[inputs]]\ndirectories = "stacks/*"\n[[inputs]]\ndirectories = "more/*"\n'
        '[output]\ndirectory = "out"\n'
    )
    with pytest.raises(InputError, match="would both write"):
        wplan.plan_stacks(load_workflow(path))


def test_an_output_directory_that_cannot_be_made_is_an_input_error(tmp_path):
    root = _tree(tmp_path)
    (root / "out").write_text("a file where the output folder should be")
    with pytest.raises(InputError, match="cannot create the output directory"):
        wrun.run_workflow(load_workflow(_flow(root)))


def test_a_run_reports_what_it_did_and_how_long_it_took(tmp_path):
    import time

    root = _tree(tmp_path)
    workflow = load_workflow(_flow(root, extra='name = "a/b/{stack}.tif"\n'))  # nested
    seen = []
    wrun.run_workflow(workflow, dry_run=True, on_plan=lambda todo, n: seen.append(
        (sorted(why for _, why in todo), n)))
    assert seen == [(["new", "new"], 0)]
    start = time.perf_counter()
    first = wrun.run_workflow(workflow)
    elapsed = time.perf_counter() - start
    assert (first.planned, sorted(first.done), first.skipped, first.failed) == (
        2, ["stacks/s10", "stacks/s2"], [], [])
    assert elapsed - 0.05 <= first.seconds <= elapsed
    second = wrun.run_workflow(workflow)
    assert (second.done, second.skipped, second.run_id) == (
        [], ["stacks/s2", "stacks/s10"], first.run_id + 1)
    plan = []
    dry = wrun.run_workflow(workflow, dry_run=True, on_plan=lambda todo, n: plan.append(n))
    assert (dry.run_id, dry.seconds, plan) == (0, 0.0, [2])
    assert sorted(p.name for p in (root / "out" / "a" / "b").iterdir()) == [
        "s10.tif", "s10.tif.json", "s2.tif", "s2.tif.json"]


def test_file_groups_sort_by_folder_then_name(tmp_path):
    """Groups from two folders: folder a's groups y, z come before folder b's group a."""
    for folder, group in (("b", "a"), ("a", "z"), ("a", "y")):
        (tmp_path / "shots" / folder).mkdir(parents=True, exist_ok=True)
        for i in range(2):
            (tmp_path / "shots" / folder / f"{group}_{i}.png").write_bytes(b"")
    path = tmp_path / "flow.toml"
    path.write_text(
        '[[inputs]]\nfiles = "shots/*/*.png"\ngroup_by = "^(?P<stack>[a-z])_"\n'
        '[output]\ndirectory = "out"\nname = "{parent}-{stack}.tif"\n'
    )
    planned = wplan.plan_stacks(load_workflow(path))
    assert [(s.id, s.output.name) for s in planned] == [
        ("shots/a#y", "a-y.tif"), ("shots/a#z", "a-z.tif"), ("shots/b#a", "b-a.tif")]
    assert [Path(p).name for p in planned[1].paths] == ["z_0.png", "z_1.png"]


def test_empty_inputs_are_named_by_their_number_and_reported_when_allowed(tmp_path):
    root = _tree(tmp_path)
    path = root / "flow.toml"
    path.write_text(
        '[[inputs]]\ndirectories = "stacks/*"\n[[inputs]]\ndirectories = "drop/*"\n'
        '[[inputs]]\nfiles = "later/*.png"\n[output]\ndirectory = "out"\n'
    )
    with pytest.raises(wplan.NoInputsYet, match=r"\[\[inputs\]\] #2: directories"):
        wplan.plan_stacks(load_workflow(path))
    reported = []
    stacks = wplan.plan_stacks(load_workflow(path), empty_ok=True, on_empty=reported.append)
    assert len(stacks) == 2 and len(reported) == 2
    assert "#2: directories = 'drop/*'" in reported[0] and "#3: files" in reported[1]
    assert len(wplan.plan_stacks(load_workflow(path), empty_ok=True)) == 2  # no callback


def test_fingerprint_follows_a_lens_profile_outside_the_stack(tmp_path):
    root = _tree(tmp_path)
    lens = root / "stacks" / "lens.toml"
    lens.write_text(
        'name = "test lens"\nfocal_length_mm = 12.5\nf_number = 1.4\n'
        "[sensor]\npixel_pitch_um = 4.65\nwidth_px = 32\nheight_px = 24\n"
    )
    folder = root / "stacks" / "s2"
    frames = sorted(folder.glob("*.png"))
    (folder / "stack.toml").write_text(
        'lens = "../lens.toml"\nkind = "focal-stack"\n' + "".join(
            f'[[frames]]\nfile = "{f.name}"\nimage_distance_mm = {12.6 + 0.05 * n}\n'
            for n, f in enumerate(frames))
    )
    stack = wplan.plan_stacks(load_workflow(_flow(root)))[0]
    assert stack.id == "stacks/s2" and stack.options.lens is None
    before = wplan.fingerprint(stack, _sha)
    lens.write_text(lens.read_text().replace("f_number = 1.4", "f_number = 2.0"))
    assert wplan.fingerprint(stack, _sha) != before


def test_groups_sort_by_their_name_not_their_files_and_any_regex_groups(tmp_path):
    """The regex takes the stack from the end of the name: group a's files (2_a, 4_a)
    sort after group b's (1_b, 3_b), but group a comes first. A regex may begin with
    any letter (only the word "directory" means the folder)."""
    folder = tmp_path / "shots"
    folder.mkdir()
    for name in ("1_b.png", "2_a.png", "3_b.png", "4_a.png", "stray.png"):
        (folder / name).write_bytes(b"")
    path = tmp_path / "flow.toml"
    text = ('[[inputs]]\nfiles = "shots/[0-9]*.png"\ngroup_by = "z?_(?P<stack>[a-z])[.]png$"\n'
            '[output]\ndirectory = "out"\n')
    path.write_text(text)
    planned = wplan.plan_stacks(load_workflow(path))
    assert [(s.id, [Path(p).name for p in s.paths]) for s in planned] == [
        ("shots#a", ["2_a.png", "4_a.png"]), ("shots#b", ["1_b.png", "3_b.png"])]
    path.write_text(text.replace("[0-9]*.png", "*.png"))
    with pytest.raises(InputError, match=r"stray\.png does not match group_by"):
        wplan.plan_stacks(load_workflow(path))


def test_outputs_below_a_glob_part_followed_by_fixed_parts(tmp_path):
    inputs = tmp_path / "in"
    out = (inputs / "out").resolve()
    assert wplan._excluded_outputs(str(inputs / "*" / "frames"), out) == out
    assert wplan._excluded_outputs(str(inputs / "*" / "frames" / "*.png"), out) == out
