"""What ``flexdof stack --frame-guard`` costs over the default path, as whole processes.

    python tests/benchmarks/bench_frame_guard.py [--rounds 5] [--threads 2] [--out DIR]
    python tests/benchmarks/bench_frame_guard.py --baseline ../main  # before/after

On pcb7 and pcb10 (``pcb7/pcb_*.jpg``, ``pcb10/pcb_*.JPG``, as in ``bench_vs_peer.py``)
each round runs ``flexdof stack FRAMES -o OUT.tif --threads N`` with and without
``--frame-guard``, for this checkout and, with ``--baseline``, another one (e.g. a git
worktree of main), all in the same rounds, in the orders of a balanced Latin square
(:func:`bench_vs_peer.balanced_orders`) after one unrecorded warm-up round. Every
command runs as a whole process through :func:`bench_vs_peer.run_process` (wall time,
peak RSS, CPU time from rusage); each checkout is put first on ``sys.path`` by a small
``python -c`` launcher, so neither depends on ``PYTHONPATH`` or the editable install.

Reported: median [min-max] per command; the ratio guard/default per checkout and stack,
as the median of the per-round (paired) ratios and as the ratio of medians, of wall and
CPU time (CPU time is far less sensitive to other load on a shared machine); and the
median stage timings of the sidecars (``timings_s``; the kernel runs beside the
accumulation, so their times overlap). Writes ``frame_guard.md`` / ``frame_guard.json``
to ``--out`` (default ``tests/benchmarks/results/speed/``).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("bench_vs_peer", HERE / "bench_vs_peer.py")
peer = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(peer)

REPO = HERE.parents[1]
TARGET = 1.2  # guard/default wall time asked for (issue 13's follow-up)


def commands(frames: list[str], tmp: Path, checkouts: dict[str, Path], threads: int) -> dict:
    """``{label: argv}``: default and ``--frame-guard`` for each checkout."""
    cmds = {}
    for name, checkout in checkouts.items():
        for mode, extra in (("default", []), ("guard", ["--frame-guard"])):
            out = tmp / f"{name}_{mode}.tif"
            cmds[f"{name} {mode}"] = [
                sys.executable, "-c", peer.BASELINE_SNIPPET, str(checkout),
                "stack", *frames, "-o", str(out), "--threads", str(threads), "-q", *extra,
            ]  # fmt: skip
    return cmds


def ratio(runs: dict[str, list[dict]], top: str, bottom: str) -> dict:
    """``top``/``bottom`` of wall and CPU time: paired (per round) and of medians."""
    out = {}
    for key in ("wall_s", "cpu_s"):
        paired = [a[key] / b[key] for a, b in zip(runs[top], runs[bottom])]
        medians = [statistics.median(m[key] for m in runs[name]) for name in (top, bottom)]
        out[key] = {"paired": peer.summary(paired), "of_medians": medians[0] / medians[1]}
    return out


def ratios(runs: dict[str, list[dict]], checkouts) -> dict:
    """Guard/default per checkout and, with a baseline, this default/base default."""
    out = {f"{name} guard/default": ratio(runs, f"{name} guard", f"{name} default")
           for name in checkouts}  # fmt: skip
    if "base" in checkouts:
        out["default this/base"] = ratio(runs, "this default", "base default")
    return out


def report(results: dict, args, checkouts) -> str:
    lines = [
        "# `flexdof stack --frame-guard` against the default path (whole processes)",
        "",
        f"`python tests/benchmarks/bench_frame_guard.py --rounds {args.rounds} --threads "
        f"{args.threads}{' --baseline ' + str(args.baseline) if args.baseline else ''}` — "
        f"{args.rounds} rounds after one warm-up round, orders from a balanced Latin square; "
        "median [min-max]. Checkouts: "
        + ", ".join(f"`{name}` = {path}" for name, path in checkouts.items())
        + ".",
        "",
        *([f"**Note:** {args.note}", ""] if args.note else []),
        *peer.command_table(results),
    ]
    lines += [
        "",
        "Ratios: median of the per-round (paired) ratios [min-max]; ratio of medians. "
        f"Guard/default per checkout (target: wall <= {TARGET}); with a baseline, this "
        f"checkout's default path against the baseline's (issue 13: at most {TARGET}).",
        "",
        "| stack | ratio | wall paired | wall of medians | CPU paired | CPU of medians |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for stack, res in results.items():
        for name, r in res["ratios"].items():
            wall, cpu = r["wall_s"], r["cpu_s"]
            lines.append(
                f"| {stack} | {name} | {peer.fmt(wall['paired'])} | {wall['of_medians']:.2f} | "
                f"{peer.fmt(cpu['paired'])} | {cpu['of_medians']:.2f} |"
            )
    return "\n".join(lines + peer.stage_table(results))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=peer.DEFAULT_OUT)
    parser.add_argument(
        "--baseline", type=Path, help="another flexdof checkout, run in the same rounds"
    )
    parser.add_argument("--note", help="a line for the report (e.g. what the baseline is)")
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error("--rounds must be >= 1")
    checkouts = {"this": REPO}
    if args.baseline:
        checkouts = {"base": args.baseline.resolve(), **checkouts}

    def log(msg):
        print(msg, flush=True)

    env = peer.environment(None)
    env["niceness"] = os.nice(0)  # the commands inherit it (a shared machine: nice -n 19)
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench_frame_guard_") as tmp:
        for stack, pattern in peer.STACKS.items():
            frames = peer.frames_of(pattern)
            log(f"{stack}: {len(frames)} frames")
            cmds = commands(frames, Path(tmp), checkouts, args.threads)
            runs = peer.alternate(cmds, args.rounds, Path(tmp), log)
            results[stack] = {
                "frames": len(frames),
                "runs": runs,
                "commands": peer.summarise(runs)["commands"],
                "ratios": ratios(runs, checkouts),
            }
    env["loadavg_end"] = os.getloadavg()
    md = report(results, args, checkouts)
    md += (
        "\n\nMachine: "
        + ", ".join(f"{k} {v}" for k, v in env.items() if k not in ("loadavg_start", "loadavg_end"))
        + f"; load average (1/5/15 min) at start {env['loadavg_start']}, at end "
        f"{env['loadavg_end']}.\n"
    )
    payload = {
        "environment": env,
        "rounds": args.rounds,
        "threads": args.threads,
        "checkouts": {name: str(path) for name, path in checkouts.items()},
        "results": results,
    }
    peer.write_report(args.out, "frame_guard", md, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
