"""RAW stacks: the reduced copies from LibRaw's half-size decode against the full decode.

    python tests/benchmarks/bench_raw_previews.py [--frames 6] [--rounds 3] [--out FILE]

A stack of ``--frames`` copies of the real Canon 550D DNG (``../shared/data/raw-dng-canon550d``)
with ``--blur-span-px 20``; per round, alternately, the whole ``flexdof stack`` process with
previews from the half-size decode (this checkout) and with previews from the full decode
(``read_preview`` patched back to decoding fully, as before stop 28); wall time and the job's
own ``align`` stage (which reads every frame's preview). Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from real_stacks import SHARED

DNG = SHARED / "raw-dng-canon550d" / "colorchart.dng"
# the same job with read_preview's RAW branch off: every preview from the full decode
FULL_DECODE = (
    "import sys; from pipeline.io import read; "
    "orig = read._read_raw; read._read_raw = lambda p, half_size=False: orig(p); "
    "from pipeline.cli import main; sys.exit(main(sys.argv[1:]))"
)


def run(cmd: list[str], out: Path) -> tuple[float, float]:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    wall = time.perf_counter() - t0
    return wall, json.loads(out.with_name(out.name + ".json").read_text())["timings_s"]["align"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if not DNG.is_file():
        raise SystemExit(f"{DNG}: not found (the shared data folder is needed)")
    results: dict[str, list[tuple[float, float]]] = {"half-size previews": [], "full decode": []}
    with tempfile.TemporaryDirectory() as tmp:
        stack = Path(tmp) / "stack"
        stack.mkdir()
        for i in range(args.frames):
            shutil.copy(DNG, stack / f"frame_{i:02d}.dng")
        out = Path(tmp) / "out.tif"
        job = ["stack", str(stack), "-o", str(out), "-q", "--blur-span-px", "20", "--threads", "2"]
        commands = {
            "half-size previews": [sys.executable, "-m", "pipeline.cli", *job],
            "full decode": [sys.executable, "-c", FULL_DECODE, *job],
        }
        run(commands["half-size previews"], out)  # warm-up
        for r in range(args.rounds):
            order = list(commands) if r % 2 == 0 else list(commands)[::-1]
            for name in order:
                results[name].append(run(commands[name], out))
    lines = [
        f"{args.frames} copies of `{DNG.name}` (1734x1156), {args.rounds} alternating rounds, "
        "median [min-max]:",
        "",
        "| previews | wall s | align stage s |",
        "|---|---|---|",
    ]
    for name, runs in results.items():
        cells = []
        for k in (0, 1):
            values = [r[k] for r in runs]
            cells.append(f"{statistics.median(values):.2f} [{min(values):.2f}-{max(values):.2f}]")
        lines.append(f"| {name} | {' | '.join(cells)} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
