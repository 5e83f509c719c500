"""The mutation recheck applies a session's survivor where it was, not where its number
now points (``tests/mutation/run.py``; needs the ``mutation`` extra, cosmic-ray).

cosmic-ray numbers a mutant by its occurrence among the operator's sites; code added above
the site since the session shifts that number. These tests write a module, record the diff
of a mutant on it, add a site above, and check that the recheck finds the same change.
"""

from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

import pytest

pytest.importorskip("cosmic_ray", reason="the mutation extra (cosmic-ray) is not installed")
if shutil.which("cosmic-ray") is None:
    pytest.skip("the cosmic-ray command is not on PATH", allow_module_level=True)

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("mutation_run", ROOT / "tests/mutation/run.py")
run = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(run)

BEFORE = "def f(a, b):\n    x = a - 1\n    return x - b\n"
# one more Sub site above both: the session's occurrence 1 (``x - b``) is now number 2
AFTER = "def g(c):\n    return c - 7\n\n\n" + BEFORE


def _mutant(tmp_path: Path, occurrence: int) -> dict:
    """A survivor as the session records it: ``occurrence`` of Sub -> Add on BEFORE, with
    cosmic-ray's own diff of it."""
    module = tmp_path / "m.py"
    module.write_text(BEFORE)
    m = {"module_path": "m.py", "operator_name": "core/ReplaceBinaryOperator_Sub_Add",
         "occurrence": occurrence, "start_pos": [0, 0]}
    mutated = run._apply(tmp_path, m, occurrence)
    assert mutated is not None
    _, removed, added = run._landing(BEFORE.encode(), mutated)
    m["diff"] = "--- a/m.py\n+++ b/m.py\n@@\n" + "".join(
        f"-{r}\n" for r in removed) + "".join(f"+{a}\n" for a in added)
    return m


def test_a_shifted_survivor_is_found_by_its_diff(tmp_path):
    m = _mutant(tmp_path, 1)  # ``return x - b`` -> ``return x + b``
    (tmp_path / "m.py").write_text(AFTER)
    mutated, line = run.locate(tmp_path, m)
    assert "return x + b" in mutated.decode() and "c - 7" in mutated.decode()
    assert AFTER.splitlines()[line - 1].strip() == "return x - b"
    # the recorded number alone would mutate another site
    wrong = run._apply(tmp_path, m, 1).decode()
    assert "return x + b" not in wrong


def test_a_survivor_whose_code_is_gone_is_reported_gone(tmp_path):
    m = _mutant(tmp_path, 0)  # ``x = a - 1`` -> ``x = a + 1``
    (tmp_path / "m.py").write_text(BEFORE.replace("a - 1", "a * 1"))
    assert run.locate(tmp_path, m) is None
