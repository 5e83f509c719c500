"""CLI start-up (issue 15): ``flexdof --help`` and ``flexdof COMMAND --help`` as whole processes.

    python tests/benchmarks/bench_startup.py [--repeats 7] [--out DIR]

Times, as whole processes (wall time spawn to reap, CPU time and peak RSS from rusage,
measured like ``bench_vs_peer.py`` does; median [min-max] of N rounds after one warm-up
round, commands alternated within each round and the order rotated per round): the
interpreter alone (``python -c pass``, the floor), ``flexdof --help`` and ``flexdof
COMMAND --help`` for every sub-command the parser registers (found by building the
parser once, in this process). Then ``python -X importtime`` of
``import pipeline.cli`` and of ``pipeline.cli.build_parser()`` (what every ``--help``
and every command pays): the top 15 imports by cumulative time, and the cost of each
top-level package, median of 3 runs each.

Writes ``startup.md`` / ``startup.json`` to ``--out`` (default
``tests/benchmarks/results/speed/``).
"""

from __future__ import annotations

import argparse
import collections
import datetime
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from bench_vs_peer import run_process  # noqa: E402  (the same whole-process measurement)

DEFAULT_OUT = HERE / "results/speed"
TARGET_S = 0.3


def flexdof_exe() -> list[str]:
    exe = Path(sys.executable).with_name("flexdof")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "pipeline.cli"]


def sub_commands() -> list[str]:
    from pipeline.cli import build_parser

    parser = build_parser()
    for action in parser._actions:  # the one _SubParsersAction
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices)
    return []


def timings(cmds: dict[str, list[str]], repeats: int) -> dict[str, list[dict]]:
    """Wall, CPU and peak RSS of every command, ``repeats`` rotated rounds after a warm-up."""
    names = list(cmds)
    for name in names:
        run_process(cmds[name], HERE)
    out = {name: [] for name in names}
    for r in range(repeats):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            out[name].append(run_process(cmds[name], HERE))
    return out


def importtime(code: str, runs: int = 3) -> tuple[list[dict], list[dict], float]:
    """Top 15 by cumulative time, top-level packages, and the total (ms), medians of ``runs``."""
    per_run = []
    for _ in range(runs):
        proc = subprocess.run(
            [sys.executable, "-X", "importtime", "-c", code],
            capture_output=True,
            text=True,
            check=True,
        )
        rows = []
        for line in proc.stderr.splitlines():
            if not line.startswith("import time:") or "[us]" in line:
                continue
            self_us, cum_us, name = line[len("import time:") :].split("|")
            depth = (len(name) - len(name.lstrip())) // 2  # one level per two spaces
            rows.append((name.strip(), depth, int(self_us), int(cum_us)))
        per_run.append(rows)
    cum = collections.defaultdict(list)
    top_level = collections.defaultdict(list)
    totals = []
    for rows in per_run:
        first_level = collections.Counter()
        for name, _depth, self_us, c in rows:
            cum[name].append(c)
            first_level[name.split(".")[0]] += self_us  # own time of all its modules
        for pkg, c in first_level.items():
            top_level[pkg].append(c)
        totals.append(sum(c for _n, depth, _s, c in rows if depth == 0))
    top = sorted(
        ({"module": n, "cumulative_ms": statistics.median(v) / 1000} for n, v in cum.items()),
        key=lambda d: -d["cumulative_ms"],
    )[:15]
    pkgs = sorted(
        ({"package": n, "self_ms": statistics.median(v) / 1000} for n, v in top_level.items()),
        key=lambda d: -d["self_ms"],
    )
    return top, pkgs, statistics.median(totals) / 1000


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    exe = flexdof_exe()
    cmds = {"python -c pass": [sys.executable, "-c", "pass"], "flexdof --help": [*exe, "--help"]}
    for command in sub_commands():
        cmds[f"flexdof {command} --help"] = [*exe, command, "--help"]
    load_start = os.getloadavg()
    runs = timings(cmds, args.repeats)
    load_end = os.getloadavg()
    stats = {
        name: {
            key: {
                "median": statistics.median(m[key] for m in v),
                "min": min(m[key] for m in v),
                "max": max(m[key] for m in v),
            }
            for key in ("wall_s", "cpu_s", "peak_rss_mib")
        }
        for name, v in runs.items()
    }
    imports = {}
    for label, code in (
        ("import pipeline.cli", "import pipeline.cli"),
        ("build_parser()", "import pipeline.cli; pipeline.cli.build_parser()"),
    ):
        top, pkgs, total = importtime(code)
        imports[label] = {
            "code": code,
            "top15_cumulative": top,
            "top_level_packages": pkgs,
            "total_ms": total,
        }

    lines = [
        "# flexdof start-up (whole processes)",
        "",
        f"`python tests/benchmarks/bench_startup.py` — {args.repeats} rounds after a warm-up, "
        f"commands alternated, order rotated per round; median [min-max]. Target for "
        f"`flexdof --help` and `flexdof stack --help`: <= {TARGET_S} s.",
        "",
        "Wall time suffers from other load on the machine; CPU time (user + system, rusage) "
        "much less so: on an idle machine wall is about CPU time for these single-threaded "
        "start-ups.",
        "",
        "| command | wall s | CPU s | peak RSS MiB | wall over target |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, s in stats.items():
        w, c, m = s["wall_s"], s["cpu_s"], s["peak_rss_mib"]
        flag = "yes" if w["median"] > TARGET_S and name.startswith("flexdof") else ""
        lines.append(
            f"| `{name}` | {w['median']:.3f} [{w['min']:.3f}-{w['max']:.3f}] | "
            f"{c['median']:.3f} [{c['min']:.3f}-{c['max']:.3f}] | {m['median']:.0f} | {flag} |"
        )
    for imp in imports.values():
        lines += [
            "",
            f'## `python -X importtime -c "{imp["code"]}"`',
            "",
            f"Median of 3 runs; first-level imports sum to {imp['total_ms']:.0f} ms.",
            "",
            "Top 15 by cumulative time:",
            "",
            "| module | cumulative ms |",
            "| --- | --- |",
        ]
        lines += [f"| {d['module']} | {d['cumulative_ms']:.1f} |" for d in imp["top15_cumulative"]]
        lines += [
            "",
            "Own (self) import time summed over all modules of each top-level package (these add "
            "up to the total; >= 5 ms):",
            "",
            "| package | self ms |",
            "| --- | --- |",
        ]
        lines += [
            f"| {d['package']} | {d['self_ms']:.1f} |"
            for d in imp["top_level_packages"]
            if d["self_ms"] >= 5.0
        ]
    lines += [
        "",
        f"Date {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, {os.cpu_count()} CPUs, "
        f"load average at start {load_start}, at end {load_end}.",
    ]
    md = "\n".join(lines) + "\n"
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "startup.md").write_text(md)
    payload = {"repeats": args.repeats, "commands": stats, "importtime": imports}
    (args.out / "startup.json").write_text(json.dumps(payload, indent=2) + "\n")
    print(md)
    print(f"wrote {args.out / 'startup.md'} and .json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
