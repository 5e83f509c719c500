"""The speed benchmark's command orders (tests/benchmarks/bench_vs_peer.py): balanced, so
no command is always measured right after the same neighbour (a process run after
focus-stack is 0.1-0.2 s slower on pcb7: the benchmark must not favour either side)."""

from __future__ import annotations

import importlib.util
import itertools
from collections import Counter
from pathlib import Path

import pytest

_SPEC = importlib.util.spec_from_file_location(
    "bench_vs_peer", Path(__file__).parent / "benchmarks" / "bench_vs_peer.py"
)
bench = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench)


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6, 7])
def test_every_command_follows_every_other_equally_often(n):
    orders = bench.balanced_orders(n)
    assert len(orders) == (n if n % 2 == 0 else 2 * n)
    assert all(sorted(order) == list(range(n)) for order in orders)
    follows = Counter((a, b) for order in orders for a, b in itertools.pairwise(order))
    assert set(follows) == {(a, b) for a in range(n) for b in range(n) if a != b}
    assert len(set(follows.values())) == 1
    firsts = Counter(order[0] for order in orders)
    assert set(firsts) == set(range(n)) and len(set(firsts.values())) == 1


def test_the_baseline_runs_from_the_checkout_named_and_only_from_it(tmp_path, monkeypatch):
    """``--baseline`` given relative to the caller's directory is resolved before the
    children run elsewhere, and the child refuses to run a flexdof imported from anywhere
    but the checkout named (a relative path once ran the installed checkout as its own
    baseline). A copy of the package in another folder stands for the other checkout."""
    import shutil
    import subprocess
    import sys

    other = tmp_path / "other"
    shutil.copytree(Path(bench.REPO) / "pipeline", other / "pipeline",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    monkeypatch.chdir(tmp_path)
    cmd = bench.commands_for(["a.jpg"], tmp_path / "t", None, decode=False, baseline="other")
    base = cmd["flexdof@base"]
    assert base[3] == str(other.resolve())
    probe = [sys.executable, "-c", bench.BASELINE_SNIPPET]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    ran = subprocess.run([*probe, base[3], "--version"], cwd=elsewhere, capture_output=True)
    assert ran.returncode == 0, ran.stderr
    missing = subprocess.run([*probe, str(tmp_path / "no-such"), "--version"], cwd=elsewhere,
                             capture_output=True, text=True)  # fmt: skip
    assert missing.returncode != 0 and "imported pipeline from" in missing.stderr
