"""Where the wall time of one `flexdof stack` goes, stage by stage (issue 15).

Runs the CLI's own code path in a fresh process per round (``--rounds``), with wall-clock
stamps around the stages (imports, load, previews, alignment, blur-span fit, kernel,
accumulation, deconvolution, write), alternating this checkout and ``--baseline`` (another
checkout, e.g. ``git worktree add ../base COMMIT``), and prints the median duration of each
stage as a markdown table. Stages that run side by side (the kernel beside the accumulation
since issue 15) are shown as they happen: their durations overlap.

    python tests/benchmarks/stage_timeline.py ../shared/data/focusstack-pcb/pcb10 \\
        --baseline ../base --rounds 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# the stamped functions: (module, attribute); missing ones (older checkouts) are skipped
STAGES = [
    ("pipeline.jobs.stack", "load"),
    ("pipeline.jobs.stack", "read_previews"),
    ("pipeline.jobs.stack", "_align"),
    ("pipeline.core.defocus", "estimate_blur_span"),
    ("pipeline.jobs.stack", "stack_kernel"),
    ("pipeline.jobs.stack", "accumulate"),
    ("pipeline.jobs.stack", "restore_image"),
    # the steps that keep the result to the frames (issue 13; absent before stop 23)
    ("pipeline.jobs.stack", "restore_ends"),
    ("pipeline.jobs.stack", "keep_inner_detail"),
    ("pipeline.jobs.stack", "quiet_flat_areas"),
    ("pipeline.jobs.stack", "clip_to_frames"),
    ("pipeline.jobs.stack", "keep_to_end_frames"),
    ("pipeline.jobs.stack", "write_result"),
]

CHILD = """
import importlib, json, sys, time
t0 = time.perf_counter()
spans = {}
from pipeline import cli
cli.tune_process()
import pipeline.jobs.stack
spans["imports"] = (0.0, time.perf_counter() - t0)
def stamp(module, name):
    mod = importlib.import_module(module)
    if not hasattr(mod, name):
        return
    f = getattr(mod, name)
    def timed(*a, **k):
        start = time.perf_counter() - t0
        try:
            return f(*a, **k)
        finally:
            spans[name] = (start, time.perf_counter() - t0)
    setattr(mod, name, timed)
for module, name in json.loads(sys.argv[1]):
    stamp(module, name)
code = cli.main(["stack", sys.argv[2], "-o", sys.argv[3], "-q"])
spans["process"] = (0.0, time.perf_counter() - t0)
print(json.dumps(spans))
sys.exit(code)
"""


def run_once(checkout: Path, stack: str, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(STAGES), stack, str(out)],
        env=env,
        # away from any checkout: ``python -c`` puts its working directory first on sys.path,
        # ahead of PYTHONPATH (run from the repository, the baseline ran this checkout's code)
        cwd=out.parent,
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise SystemExit(f"{checkout}: flexdof stack failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stack", help="a stack folder or glob")
    parser.add_argument("--baseline", type=Path, help="another checkout, run in the same rounds")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args(argv)
    checkouts = {"this": ROOT}
    if args.baseline:
        checkouts["baseline"] = args.baseline.resolve()
    stack = str(Path(args.stack).resolve())  # the children run in a temporary directory
    runs: dict[str, list[dict]] = {name: [] for name in checkouts}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds + 1):  # round 0 warms the caches and is dropped
            for name, checkout in checkouts.items():
                out = Path(tmp) / f"{name}.tif"
                spans = run_once(checkout, stack, out)
                if r:
                    runs[name].append(spans)
                print(f"round {r} {name}: {spans['process'][1]:.2f} s", file=sys.stderr)
    names = ["imports", *(n for _, n in STAGES), "process"]
    print(f"Stage wall times of `flexdof stack {args.stack}` (median of {args.rounds} rounds, s; "
          "start-end from the process start in brackets)\n")
    print("| stage | " + " | ".join(checkouts) + " |")
    print("|---|" + "---|" * len(checkouts))
    for stage in names:
        cells = []
        for name in checkouts:
            found = [s[stage] for s in runs[name] if stage in s]
            if not found:
                cells.append("-")
                continue
            start = statistics.median(a for a, _ in found)
            end = statistics.median(b for _, b in found)
            span = statistics.median(b - a for a, b in found)
            cells.append(f"{span:.2f} [{start:.2f}-{end:.2f}]")
        print(f"| {stage} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
