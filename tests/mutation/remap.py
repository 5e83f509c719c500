"""Move a finished session's survivors onto today's version of their module, so that
``run.py --recheck`` applies the same mutants after the module changed.

``cosmic-ray apply`` finds a mutant by its operator's occurrence number; a change that
adds or removes an operator's occurrences before it makes the number point at another
mutant (the recheck then reports on the wrong one). This copies the session and rewrites
each survivor's occurrence and position to today's: its line is mapped through a diff of
the module at REV and today (survivors on changed lines are reported, not mapped), and
matched by operator, column and rank among the variants at that node.

    python tests/mutation/remap.py SESSION.sqlite OUT_DIR MODULE REV
    python tests/mutation/run.py --recheck OUT_DIR MODULE

``MODULE`` is under ``pipeline/`` (as for run.py), ``REV`` the commit the session was run on.
"""

from __future__ import annotations

import difflib
import shutil
import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def positions(conn) -> dict:
    """``(operator, row, col) -> [(occurrence, row, end row), ...]`` sorted by occurrence
    (an operator with several variants at one node, like NumberReplacer, has several)."""
    out: dict = {}
    for op, occ, r0, c0, r1 in conn.execute(
        "select operator_name, occurrence, start_pos_row, start_pos_col, end_pos_row "
        "from mutation_specs"
    ):
        out.setdefault((op, r0, c0), []).append((occ, r0, r1))
    return {k: sorted(v) for k, v in out.items()}


def line_map(old: list[str], new: list[str]) -> dict[int, int]:
    """1-based old line -> new line, for the lines the diff keeps unchanged."""
    out = {}
    for block in difflib.SequenceMatcher(None, old, new, autojunk=False).get_matching_blocks():
        for k in range(block.size):
            out[block.a + k + 1] = block.b + k + 1
    return out


def main(argv: list[str]) -> int:
    session, out_dir, module, rev = Path(argv[0]), Path(argv[1]), argv[2], argv[3]
    path = f"pipeline/{module}"
    old = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout.splitlines()
    new = (ROOT / path).read_text().splitlines()
    lines = line_map(old, new)
    with tempfile.TemporaryDirectory(prefix="flexdof-remap-") as tmp:
        config = Path(tmp) / "config.toml"
        config.write_text(f'[cosmic-ray]\nmodule-path = "{path}"\ntimeout = 60\n'
                          'excluded-modules = []\ntest-command = "true"\n\n'
                          '[cosmic-ray.distributor]\nname = "local"\n')
        today = Path(tmp) / "today.sqlite"
        subprocess.run(["cosmic-ray", "init", str(config), str(today)], cwd=ROOT, check=True,
                       capture_output=True)
        index = positions(sqlite3.connect(today))
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / session.name
    shutil.copy(session, target)
    db = sqlite3.connect(target)
    before = positions(db)
    rows = db.execute(
        "select m.job_id, m.operator_name, m.occurrence, m.start_pos_row, m.start_pos_col "
        "from mutation_specs m join work_results r on r.job_id = m.job_id "
        "where r.test_outcome = 'SURVIVED'"
    ).fetchall()
    lost = 0
    for job, op, occ, row, col in rows:
        olds = before[(op, row, col)]
        hits = index.get((op, lines.get(row, -1), col))
        if row not in lines or not hits or len(hits) != len(olds):
            print(f"NOT MAPPED {op} #{occ} line {row}: {old[row - 1].strip()[:60]}")
            lost += 1
            continue
        occ_new, row_new, end_new = hits[[o[0] for o in olds].index(occ)]
        db.execute("update mutation_specs set occurrence=?, start_pos_row=?, end_pos_row=? "
                   "where job_id=?", (occ_new, row_new, end_new, job))
    db.commit()
    print(f"{len(rows) - lost} of {len(rows)} survivors mapped into {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
