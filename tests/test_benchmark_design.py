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
