"""Mutation testing of the core modules with cosmic-ray (MIT), each module against only
the tests that cover it. Not part of CI (minutes to hours on 2 cores).

    pip install "cosmic-ray==8.7.0"
    python tests/mutation/run.py                       # every module below
    python tests/mutation/run.py core/optics.py core/spectra.py
    python tests/mutation/run.py --list                # the module -> tests table
    python tests/mutation/run.py --recheck SESSIONS core/spectra.py  # survivors of a
        # finished session against today's tests (after adding tests; cheap)

Each module is mutated in a scratch copy of the checkout (never in place), one worker,
``pytest -x`` on its test files, 60 s per mutant. Prints a table: mutants, killed,
survived, score; the sessions (``SCRATCH/<module>.sqlite``) stay for
``cr-report --show-diff --surviving-only``. Exit status 0.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if len(sys.argv) > 1 and sys.argv[1] == "--root":  # score another checkout (e.g. "before")
    ROOT = Path(sys.argv[2]).resolve()
    del sys.argv[1:3]

DECONVOLVE = ["tests/test_deconvolve.py", "tests/test_deconvolve_asymmetric.py",
              "tests/test_references.py"]

# module (under pipeline/) -> the test files that cover it
MODULES: dict[str, list[str]] = {
    "core/optics.py": ["tests/test_optics.py", "tests/test_optics_boundaries.py"],
    "core/spectra.py": ["tests/test_psf.py", "tests/test_deconvolve_asymmetric.py",
                        "tests/test_spectra.py"],
    "core/weights.py": ["tests/test_weights.py"],
    "core/stack_kernel.py": ["tests/test_stack_heart.py", "tests/test_engine.py"],
    "core/psf.py": ["tests/test_psf.py", "tests/test_issue11_kills.py"],
    "parallel/accumulate.py": ["tests/test_stack_heart.py", "tests/test_engine.py"],
    "parallel/tiling.py": ["tests/test_tiling.py", "tests/test_deconvolve_asymmetric.py"],
    "core/deconvolve/wiener.py": DECONVOLVE,
    "core/deconvolve/rl.py": DECONVOLVE,
    "core/deconvolve/sparse.py": DECONVOLVE,
    "core/align.py": ["tests/test_align.py", "tests/test_issue11_kills.py"],
    "workflow/ledger.py": ["tests/test_workflow.py", "tests/test_issue11_kills.py"],
    "tether/session.py": ["tests/test_tether_ptp.py", "tests/test_tether_emulated.py",
                          "tests/test_issue11_kills.py"],
    "tether/ptp.py": ["tests/test_tether_ptp.py"],
}

CONFIG = """[cosmic-ray]
module-path = "{module}"
timeout = 60.0
excluded-modules = []
test-command = "{python} -m pytest -x -q -p no:cacheprovider {tests}"

[cosmic-ray.distributor]
name = "local"

[cosmic-ray.filters.operators-filter]
# Binary operators are swapped among + - * / ** only: the bitwise, shift, // and %
# swaps on float arrays are ~60% of cosmic-ray's mutants and almost all crash at once
# (a TypeError is not a test of the maths); dropping them makes a module affordable.
exclude-operators = [
    "core/ReplaceBinaryOperator_.*_(FloorDiv|Mod|LShift|RShift|BitOr|BitAnd|BitXor|MatMult)$",
    "core/ReplaceBinaryOperator_(FloorDiv|Mod|LShift|RShift|BitOr|BitAnd|BitXor|MatMult)_.*",
]
"""


def scratch_copy(dest: Path) -> None:
    for item in ("pipeline", "tests", "pyproject.toml", "lens_profiles", "stacks", "workflows"):
        src = ROOT / item
        if src.is_dir():
            shutil.copytree(src, dest / item, ignore=shutil.ignore_patterns("__pycache__"))
        elif src.exists():
            shutil.copy2(src, dest / item)


def score(module: str, work: Path, sessions: Path) -> dict:
    tests = [t for t in MODULES[module] if (work / t).exists()]
    name = module.replace("/", "_")
    config = sessions / f"{name}.toml"
    session = sessions / f"{name}.sqlite"
    config.write_text(CONFIG.format(module=f"pipeline/{module}", python=sys.executable,
                                    tests=" ".join(tests)))
    run = dict(cwd=work, check=True, capture_output=True, text=True)
    subprocess.run(["cosmic-ray", "init", str(config), str(session)], **run)
    subprocess.run(["cr-filter-operators", str(session), str(config)], **run)
    subprocess.run(["cosmic-ray", "exec", str(config), str(session)], **run)
    dump = subprocess.run(["cosmic-ray", "dump", str(session)], **run).stdout
    counts = {"killed": 0, "survived": 0, "incompetent": 0, "pending": 0, "skipped": 0}
    for line in dump.splitlines():
        _, result = json.loads(line)
        if result is not None and result.get("worker_outcome") == "skipped":
            counts["skipped"] += 1
        elif result is None:
            counts["pending"] += 1
        elif result["test_outcome"] == "killed":
            counts["killed"] += 1
        elif result["test_outcome"] == "survived":
            counts["survived"] += 1
        else:
            counts["incompetent"] += 1
    total = counts["killed"] + counts["survived"]
    counts["score"] = 100.0 * counts["killed"] / total if total else float("nan")
    return counts


def survivors(session: Path) -> list[dict]:
    dump = subprocess.run(["cosmic-ray", "dump", str(session)], check=True,
                          capture_output=True, text=True).stdout
    out = []
    for line in dump.splitlines():
        job, result = json.loads(line)
        if result is not None and result.get("test_outcome") == "survived":
            out.append(job["mutations"][0])
    return out


def recheck(module: str, sessions: Path) -> None:
    """Re-run the survivors of ``module``'s session against the current tests."""
    session = sessions / f"{module.replace('/', '_')}.sqlite"
    tests = [t for t in MODULES[module] if (ROOT / t).exists()]
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    alive = []
    found = survivors(session)
    for m in found:
        with tempfile.TemporaryDirectory(prefix="flexdof-mutant-") as tmp:
            work = Path(tmp)
            scratch_copy(work)
            subprocess.run(["cosmic-ray", "apply", m["module_path"], m["operator_name"],
                            str(m["occurrence"])], cwd=work, check=True, capture_output=True)
            proc = subprocess.run(cmd, cwd=work, capture_output=True, text=True, check=False)
        line = m["start_pos"][0]
        src = (ROOT / m["module_path"]).read_text().splitlines()[line - 1].strip()
        verdict = "KILLED" if proc.returncode == 1 else "SURVIVED"
        print(f"{verdict:8s} {m['operator_name']} #{m['occurrence']} line {line}: {src[:70]}",
              flush=True)
        if verdict == "SURVIVED":
            alive.append(m)
    print(f"{module}: {len(found) - len(alive)} of {len(found)} survivors now killed")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", help="modules under pipeline/ (default: all)")
    parser.add_argument("--list", action="store_true")
    parser.add_argument("--keep", type=Path, help="folder for the sessions (default: a temp)")
    parser.add_argument("--recheck", type=Path, metavar="SESSIONS",
                        help="re-run the survivors recorded in SESSIONS with today's tests")
    args = parser.parse_args(argv)
    if args.recheck:
        for module in args.modules:
            recheck(module, args.recheck)
        return 0
    if args.list:
        for m, t in MODULES.items():
            print(f"{m:30s} {' '.join(t)}")
        return 0
    modules = args.modules or list(MODULES)
    sessions = args.keep or Path(tempfile.mkdtemp(prefix="flexdof-mutation-"))
    sessions.mkdir(parents=True, exist_ok=True)
    print(f"sessions in {sessions}")
    print(f"| {'module':28s} | mutants | killed | survived | score |")
    print(f"|{'-' * 30}|---------|--------|----------|-------|")
    for module in modules:
        with tempfile.TemporaryDirectory(prefix="flexdof-mutant-") as tmp:
            work = Path(tmp)
            scratch_copy(work)
            c = score(module, work, sessions)
        n = c["killed"] + c["survived"]
        print(f"| {module:28s} | {n:7d} | {c['killed']:6d} | {c['survived']:8d} "
              f"| {c['score']:4.0f}% |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
