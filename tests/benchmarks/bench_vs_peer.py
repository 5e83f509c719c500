"""flexdof against the peer focus stacker and against decoding alone, as whole processes (issue 15).

    python tests/benchmarks/bench_vs_peer.py --focus-stack PATH [--repeats 5] [--out DIR]
    python tests/benchmarks/bench_vs_peer.py --focus-stack PATH --scaling [--repeats 3]
    python tests/benchmarks/bench_vs_peer.py --focus-stack PATH --baseline ../base  # before/after
    python tests/benchmarks/bench_vs_peer.py --focus-stack PATH --quality  # + --method multiframe

Default mode, on pcb7 (``pcb7/pcb_*.jpg``, 7 frames 2048x1536; ``expected.jpg`` is
another tool's result and is left out) and pcb10 (``pcb10/pcb_*.JPG``, 10 frames):

* ``flexdof``: ``flexdof stack FRAMES -o OUT.tif`` (default options and threads);
* ``decode``: ``python -c`` reading every frame with ``cv2.imread(f, IMREAD_UNCHANGED)``
  one after the other (the decoder :func:`pipeline.io.read.read_frame` uses: OpenCV's
  libjpeg(-turbo) through ``cv2.imdecode``), interpreter start-up and ``import cv2``
  included;
* ``focus-stack``: ``focus-stack --output=OUT.png FRAMES`` (its defaults: all cores).

Each repeat runs the commands once, in the orders of a balanced Latin square
(:func:`balanced_orders`: over ``n`` repeats, ``2n`` for an odd number ``n`` of commands,
every command runs right after every other command equally often), after one unrecorded
warm-up round (page cache, .pyc). A plain rotation put flexdof right after focus-stack in
3 of 4 rounds, and a process that follows focus-stack (~900 MiB freed) decodes and
accumulates 0.1-0.2 s slower on this VM: numpy asks for transparent huge pages
(``madvise``), which then need compaction (pcb7 after focus-stack 1.30-1.38 s, after
flexdof 1.11-1.17 s; with ``NUMPY_MADVISE_HUGEPAGE=0`` 1.19-1.24 s after either).

Every command is timed as a whole process: wall time from spawn to reap, peak resident
memory (``ru_maxrss``) and CPU time (user + system) of the process from ``os.wait4``'s
rusage, taken by a small ``python -S`` launcher (see :data:`LAUNCHER`; its ~10 MiB is
the floor of the RSS figures). Reported: median
[min-max] per command, and the ratios flexdof/focus-stack and flexdof/decode both as
the median of the per-repeat (paired) ratios and as the ratio of medians.

``--scaling``: flexdof (and the peer, if given) on pcb7's frames repeated to 7 / 14 /
28 frames (each frame copied under new names, consecutively, so the focus order is
kept) at 3 Mpx, and the 7 frames upsampled to 4096x3072 (12 Mpx, cv2 INTER_CUBIC,
JPEG quality 95) in a temporary folder: wall time and peak RSS, alternating as above.

Writes ``vs_peer.md`` / ``vs_peer.json`` (or ``scaling.md`` / ``scaling.json``) to
``--out`` (default ``tests/benchmarks/results/speed/``). Without ``--focus-stack``, or
when the path is not an executable, the peer is skipped and the report says so.
"""

from __future__ import annotations

import argparse
import datetime
import glob
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
DATA = REPO.parent / "shared/data/focusstack-pcb"
if not DATA.is_dir():  # a worktree beside /work/main, or a clone with shared/ beside it
    DATA = Path("/work/shared/data/focusstack-pcb")
STACKS = {
    "pcb7": "pcb7/pcb_*.jpg",
    "pcb10": "pcb10/pcb_*.JPG",
}
DEFAULT_OUT = HERE / "results/speed"
DECODE_SNIPPET = (
    "import sys, cv2\n"
    "for f in sys.argv[1:]:\n"
    "    if cv2.imread(f, cv2.IMREAD_UNCHANGED) is None: sys.exit('cannot decode ' + f)\n"
)


# ----------------------------------------------------------------------------- measuring
# Peak RSS must come from a small launcher: at exec, Linux folds the *old* memory map's
# high-water mark into the new program's ru_maxrss, and a child spawned by this process
# (fork or vfork) starts from this process's map (tens to hundreds of MiB after cv2 and
# the 12 Mpx frames). So this process starts ``python -S`` (~10 MiB), which spawns the
# command, reaps it with os.wait4 and prints wall time and the command's rusage; the
# floor of every RSS figure is then that launcher's ~10 MiB, not this process's size.
LAUNCHER = """
import os, sys, time
null = os.open(os.devnull, os.O_WRONLY)
t0 = time.perf_counter()
pid = os.posix_spawnp(sys.argv[1], sys.argv[1:], os.environ,
                      file_actions=[(os.POSIX_SPAWN_DUP2, null, 1)])
_, status, ru = os.wait4(pid, 0)
wall = time.perf_counter() - t0
print(wall, ru.ru_maxrss, ru.ru_utime + ru.ru_stime, os.waitstatus_to_exitcode(status))
"""


# Python caches compiled modules (``__pycache__``) as every installed package does, unless
# PYTHONDONTWRITEBYTECODE is set (some sandboxes set it): then each run recompiles every
# module of an editable checkout (~0.1 s for flexdof), which no user of a wheel pays.
CHILD_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def run_process(cmd: list[str], cwd: Path) -> dict:
    """Run ``cmd`` to completion: wall seconds, the command's peak RSS (MiB) and CPU seconds."""
    with tempfile.TemporaryFile() as err:
        proc = subprocess.run(
            [sys.executable, "-S", "-c", LAUNCHER, *cmd],
            cwd=cwd,
            env=CHILD_ENV,
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            check=False,
        )
        fields = proc.stdout.split()
        if proc.returncode != 0 or len(fields) != 4 or fields[3] != "0":
            err.seek(0)
            tail = err.read().decode(errors="replace")[-2000:]
            raise RuntimeError(f"{' '.join(cmd[:3])} ... failed ({proc.stdout.strip()}):\n{tail}")
    wall, maxrss_kib, cpu, _rc = fields
    return {
        "wall_s": float(wall),
        "peak_rss_mib": int(maxrss_kib) / 1024,  # Linux: KiB
        "cpu_s": float(cpu),
    }


def flexdof_exe() -> list[str]:
    exe = Path(sys.executable).with_name("flexdof")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "pipeline.cli"]


# runs flexdof from the checkout named first (an absolute path: the children run in a
# temporary directory), and refuses to run any other: until stop 47 a relative
# ``--baseline`` was looked up from there, missed, and the installed checkout ran as its own
# baseline (so the flexdof/flexdof@base ratios of stops 41-44, run with ``../wt-...`` paths,
# most likely compared a commit with itself)
BASELINE_SNIPPET = (
    "import sys, os; base = sys.argv.pop(1); sys.path.insert(0, base); import pipeline; "
    "here = os.path.dirname(os.path.dirname(os.path.abspath(pipeline.__file__))); "
    "here == base or sys.exit(f'baseline {base}: imported pipeline from {here}'); "
    "from pipeline.cli import main; sys.argv[0] = 'flexdof'; sys.exit(main())"
)


QUALITY = "flexdof multiframe"  # the quality method, with --quality


def commands_for(
    frames: list[str],
    tmp: Path,
    peer: str | None,
    decode: bool = True,
    baseline=None,
    quality: bool = False,
) -> dict:
    cmds = {"flexdof": [*flexdof_exe(), "stack", *frames, "-o", str(tmp / "flexdof.tif")]}
    if quality:
        cmds[QUALITY] = [
            *flexdof_exe(), "stack", *frames, "-o", str(tmp / "multi.tif"),
            "--method", "multiframe",
        ]  # fmt: skip
    if baseline:  # another checkout of flexdof (e.g. a git worktree of an older commit)
        cmds["flexdof@base"] = [
            sys.executable, "-c", BASELINE_SNIPPET, str(Path(baseline).resolve()),
            "stack", *frames, "-o", str(tmp / "base.tif"),
        ]  # fmt: skip
    if decode:
        cmds["decode"] = [sys.executable, "-c", DECODE_SNIPPET, *frames]
    if peer:
        cmds["focus-stack"] = [peer, f"--output={tmp / 'focus-stack.png'}", *frames]
    return cmds


def balanced_orders(n: int) -> list[list[int]]:
    """Orders of ``n`` commands (a Williams design): in ``n`` orders for even ``n`` (``2n``,
    each also reversed, for odd ``n``) every command directly follows every other one the
    same number of times, so no command always runs after the same neighbour.

    >>> balanced_orders(4)
    [[0, 1, 3, 2], [1, 2, 0, 3], [2, 3, 1, 0], [3, 0, 2, 1]]
    """
    first = [0]
    for k in range(1, n):  # 0, 1, n-1, 2, n-2, ...
        first.append((k + 1) // 2 if k % 2 else n - k // 2)
    rows = [[(i + r) % n for i in first] for r in range(n)]
    return rows if n % 2 == 0 else rows + [row[::-1] for row in rows]


def alternate(cmds: dict[str, list[str]], repeats: int, cwd: Path, log) -> dict[str, list[dict]]:
    """One warm-up round, then ``repeats`` rounds in the orders of :func:`balanced_orders`."""
    names = list(cmds)
    for name in names:
        run_process(cmds[name], cwd)
    runs: dict[str, list[dict]] = {name: [] for name in names}
    orders = balanced_orders(len(names))
    for r in range(repeats):
        order = [names[i] for i in orders[r % len(orders)]]
        for name in order:
            m = run_process(cmds[name], cwd)
            m["round"] = r
            m.update(stages_of(cmds[name]))
            runs[name].append(m)
            log(
                f"  round {r + 1}/{repeats} {name:<12} {m['wall_s']:7.2f} s "
                f"{m['peak_rss_mib']:7.0f} MiB {m['cpu_s']:6.2f} s CPU"
            )
    return runs


def stages_of(cmd: list[str]) -> dict:
    """flexdof's own stage timings (its sidecar ``OUT.json``), for the profile table."""
    if "-o" not in cmd:
        return {}
    sidecar = Path(cmd[cmd.index("-o") + 1] + ".json")
    if not sidecar.is_file():
        return {}
    return {"stages_s": json.loads(sidecar.read_text()).get("timings_s", {})}


def write_report(out: Path, name: str, md: str, payload: dict) -> None:
    """``out/name.md`` and ``out/name.json``, and the report on stdout."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text(md)
    (out / f"{name}.json").write_text(json.dumps(payload, indent=2) + "\n")
    print()
    print(md)
    print(f"wrote {out / name}.md and .json")


def command_table(results: dict) -> list[str]:
    """Markdown rows: per stack and command, median [min-max] wall time, peak RSS, CPU."""
    lines = [
        "| stack | command | wall s | peak RSS MiB | CPU s |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, res in results.items():
        for cmd, s in res["commands"].items():
            lines.append(
                f"| {name} ({res['frames']} frames) | {cmd} | {fmt(s['wall_s'])} | "
                f"{fmt(s['peak_rss_mib'], 0)} | {fmt(s['cpu_s'])} |"
            )
    return lines


def stage_table(results: dict) -> list[str]:
    """Median stage times (s, from the sidecars) of each flexdof command, per stack."""
    lines = ["", "Stages (median s, from each run's sidecar; `read` is summed over threads):", ""]
    # every stage any command reports, in the order they first appear (a stage a command
    # does not run, e.g. frame_guard without --frame-guard, is shown as nan)
    header = {}
    for res in results.values():
        for runs in res["runs"].values():
            for m in runs:
                header.update(dict.fromkeys(m.get("stages_s", {})))
    if not header:
        return []
    lines += [f"| stack | command | {' | '.join(header)} |", "|---" * (len(header) + 2) + "|"]
    for name, res in results.items():
        for cmd, runs in res["runs"].items():
            stages = [m["stages_s"] for m in runs if m.get("stages_s")]
            if not stages:
                continue
            row = [statistics.median(s.get(k, float("nan")) for s in stages) for k in header]
            lines.append(f"| {name} | {cmd} | " + " | ".join(f"{v:.2f}" for v in row) + " |")
    return lines


def summary(values: list[float]) -> dict:
    return {"median": statistics.median(values), "min": min(values), "max": max(values)}


def summarise(runs: dict[str, list[dict]]) -> dict:
    out = {}
    for name, ms in runs.items():
        out[name] = {
            key: summary([m[key] for m in ms]) for key in ("wall_s", "peak_rss_mib", "cpu_s")
        }
    ratios = {}
    for subject in (s for s in ("flexdof", QUALITY) if s in runs):
        for ref in ("focus-stack", "decode", "flexdof@base", "flexdof"):
            if ref not in runs or ref == subject:
                continue
            for key in ("wall_s", "peak_rss_mib", "cpu_s"):
                paired = [a[key] / b[key] for a, b in zip(runs[subject], runs[ref])]
                ratios[f"{subject}/{ref} {key}"] = {
                    "paired": summary(paired),
                    "of_medians": out[subject][key]["median"] / out[ref][key]["median"],
                }
    return {"commands": out, "ratios": ratios}


# ----------------------------------------------------------------------------- context
def environment(peer: str | None) -> dict:
    def git(*args):
        try:
            return subprocess.run(
                ["git", *args], cwd=REPO, capture_output=True, text=True, check=True
            ).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return None

    import cv2

    env = {
        "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S"),
        "commit": git("rev-parse", "--short", "HEAD"),
        "dirty": bool(git("status", "--porcelain", "--", "pipeline")),
        "python": platform.python_version(),
        "opencv": cv2.__version__,
        "cpus": os.cpu_count(),
        "loadavg_start": os.getloadavg(),
    }
    try:
        with open("/proc/cpuinfo") as fh:
            env["cpu"] = next(
                (line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")),
                None,
            )
    except OSError:
        pass
    if peer:
        try:
            version = subprocess.run([peer, "--version"], capture_output=True, text=True)
            text = (version.stdout + version.stderr).strip().splitlines()
            env["focus_stack"] = "; ".join(text[:2])  # version/build line, its OpenCV
        except OSError:
            env["focus_stack"] = None
    return env


def find_peer(path: str | None) -> tuple[str | None, str | None]:
    if not path:
        return None, "focus-stack skipped: no --focus-stack PATH given"
    p = shutil.which(path) or path
    if not (os.path.isfile(p) and os.access(p, os.X_OK)):
        return None, f"focus-stack skipped: {path} is not an executable file"
    return str(Path(p).resolve()), None


def frames_of(pattern: str) -> list[str]:
    files = sorted(glob.glob(str(DATA / pattern)))
    if not files:
        raise SystemExit(f"no frames match {DATA / pattern}")
    return files


def fmt(s: dict, digits: int = 2) -> str:
    return f"{s['median']:.{digits}f} [{s['min']:.{digits}f}-{s['max']:.{digits}f}]"


# ----------------------------------------------------------------------------- modes
def compare(args, peer, note, log) -> tuple[dict, str]:
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench_vs_peer_") as tmp:
        for name, pattern in STACKS.items():
            frames = frames_of(pattern)
            log(f"{name}: {len(frames)} frames")
            cmds = commands_for(
                frames, Path(tmp), peer, baseline=args.baseline, quality=args.quality
            )
            runs = alternate(cmds, args.repeats, Path(tmp), log)
            results[name] = {"frames": len(frames), "runs": runs, **summarise(runs)}
    lines = [
        "# flexdof vs focus-stack vs decoding alone (whole processes)",
        "",
        f"`python tests/benchmarks/bench_vs_peer.py` — {args.repeats} paired rounds after one "
        "warm-up round, command orders from a balanced Latin square; wall time and peak RSS "
        "(`ru_maxrss`) of each whole process; median [min-max].",
        "",
    ]
    if note:
        lines += [f"**Note:** {note}", ""]
    lines += command_table(results)
    lines += [
        "",
        "Ratios: median of the per-round (paired) ratios [min-max]; ratio of medians. CPU s "
        "(user + system of the whole process, from rusage) is much less sensitive than wall "
        "time to other load on the machine.",
        "",
        "| stack | ratio | paired median [min-max] | of medians | target |",
        "| --- | --- | --- | --- | --- |",
    ]
    targets = {
        "flexdof/focus-stack wall_s": "<= 0.5",
        "flexdof/decode wall_s": "<= 6",
        "flexdof/focus-stack peak_rss_mib": "<= 0.5",
        "flexdof/decode peak_rss_mib": "",
    }
    order = [*targets, "flexdof/focus-stack cpu_s", "flexdof/decode cpu_s"]
    order += [f"flexdof/flexdof@base {key}" for key in ("wall_s", "cpu_s", "peak_rss_mib")]
    order += [
        f"{QUALITY}/{ref} {key}"
        for ref in ("flexdof", "decode", "focus-stack")
        for key in ("wall_s", "cpu_s", "peak_rss_mib")
    ]
    for name, res in results.items():
        for key in (k for k in order if k in res["ratios"]):
            r = res["ratios"][key]
            lines.append(
                f"| {name} | {key} | {fmt(r['paired'])} | {r['of_medians']:.2f} | "
                f"{targets.get(key, '')} |"
            )
    lines += stage_table(results)
    return results, "\n".join(lines)


def _make_scaled_stacks(tmp: Path, log) -> dict[str, list[str]]:
    import cv2

    src = frames_of(STACKS["pcb7"])
    stacks = {}
    for copies in (1, 2, 4):
        folder = tmp / f"n{len(src) * copies}"
        folder.mkdir()
        files = []
        for i, f in enumerate(src):
            for c in range(copies):
                dst = folder / f"f_{i * copies + c:03d}.jpg"
                shutil.copyfile(f, dst)
                files.append(str(dst))
        stacks[f"{len(files)} frames, 3 Mpx"] = files
    folder = tmp / "12mpx"
    folder.mkdir()
    files = []
    for i, f in enumerate(src):
        image = cv2.imread(f, cv2.IMREAD_UNCHANGED)
        big = cv2.resize(image, (4096, 3072), interpolation=cv2.INTER_CUBIC)
        dst = folder / f"f_{i:03d}.jpg"
        cv2.imwrite(str(dst), big, [cv2.IMWRITE_JPEG_QUALITY, 95])
        files.append(str(dst))
    stacks[f"{len(src)} frames, 12 Mpx"] = files
    log("made " + ", ".join(stacks))
    return stacks


def scaling(args, peer, note, log) -> tuple[dict, str]:
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench_scaling_") as tmp:
        tmp = Path(tmp)
        stacks = _make_scaled_stacks(tmp, log)
        for name, frames in stacks.items():
            log(name)
            cmds = commands_for(frames, tmp, peer, decode=True)
            runs = alternate(cmds, args.repeats, tmp, log)
            results[name] = {"frames": len(frames), "runs": runs, **summarise(runs)}
    lines = [
        "# flexdof scaling: frame count and frame size (whole processes)",
        "",
        f"`python tests/benchmarks/bench_vs_peer.py --scaling` — pcb7's 7 frames copied "
        f"under new names to 14 and 28 frames, and upsampled to 4096x3072 (12 Mpx); "
        f"{args.repeats} rounds after a warm-up, orders from a balanced Latin square; "
        "median [min-max].",
        "",
    ]
    if note:
        lines += [f"**Note:** {note}", ""]
    cols = list(next(iter(results.values()))["commands"])
    head = " | ".join(f"{c} wall s | {c} peak MiB" for c in cols)
    lines += [f"| stack | {head} | flexdof/peer wall | flexdof/peer RSS |"]
    lines += ["| --- " * (1 + 2 * len(cols) + 2) + "|"]
    for name, res in results.items():
        cells = " | ".join(
            f"{fmt(res['commands'][c]['wall_s'])} | {fmt(res['commands'][c]['peak_rss_mib'], 0)}"
            for c in cols
        )
        rw = res["ratios"].get("flexdof/focus-stack wall_s")
        rm = res["ratios"].get("flexdof/focus-stack peak_rss_mib")
        lines.append(
            f"| {name} | {cells} | {rw['of_medians']:.2f} | {rm['of_medians']:.2f} |"
            if rw
            else f"| {name} | {cells} | - | - |"
        )
    return results, "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--focus-stack", help="path of the focus-stack binary (peer)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    parser.add_argument("--scaling", action="store_true", help="frame-count / size scaling")
    parser.add_argument(
        "--baseline",
        type=Path,
        help="another flexdof checkout (e.g. `git worktree add ../base COMMIT`) run in the "
        "same rounds as 'flexdof@base', for before/after ratios",
    )
    parser.add_argument(
        "--quality",
        action="store_true",
        help="also time `--method multiframe` (the quality method) in the same rounds; "
        "writes vs_peer_quality.md",
    )
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    peer, note = find_peer(args.focus_stack)
    if note:
        print(note, file=sys.stderr)

    def log(msg):
        print(msg, flush=True)

    env = environment(peer)
    results, md = (scaling if args.scaling else compare)(args, peer, note, log)
    env["loadavg_end"] = os.getloadavg()
    name = "scaling" if args.scaling else ("vs_peer_quality" if args.quality else "vs_peer")
    md += (
        "\n\nMachine: "
        + ", ".join(f"{k} {v}" for k, v in env.items() if k not in ("loadavg_start", "loadavg_end"))
        + f"; load average (1/5/15 min) at start {env['loadavg_start']}, at end "
        f"{env['loadavg_end']}.\n"
    )
    payload = {"environment": env, "peer_note": note, "repeats": args.repeats, "results": results}
    write_report(args.out, name, md, payload)
    return 0


if __name__ == "__main__":
    sys.exit(main())
