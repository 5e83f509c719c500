"""What the alignment choice (issue 13, ``pipeline.jobs.stack._keep_if_explained``) costs the
main job on stacks with a lens and focus positions, the only ones it runs on.

    python tests/benchmarks/bench_align_choice.py --baseline BASE [--rounds 7] [--out DIR]

BASE is another checkout (e.g. ``git archive`` of the commit before the change). On the
shipped motorcycle sample and on the accuracy benchmark's depth-edge scene rendered as an 8
frame stack (640x480, noisy, breathing), each round runs ``flexdof -q stack STACK -o OUT
--threads 2`` as a whole process for this checkout and BASE, in alternating order, after one
unrecorded warm-up each; reported: median wall times and the median [min-max] of the per-round
ratios. Writes ``align_choice.md`` to ``--out`` (default ``tests/benchmarks/results/speed``).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pipeline.paper.bench import scenes

REPO = Path(__file__).resolve().parents[2]
SNIPPET = (
    "import sys; sys.path.insert(0, sys.argv.pop(1)); from pipeline.cli import main; "
    "sys.argv[0] = 'flexdof'; sys.exit(main())"
)


def run(root: Path, stack: Path, out: Path) -> float:
    t0 = time.perf_counter()
    command = [sys.executable, "-c", SNIPPET, str(root), "-q", "stack", str(stack), "-o", str(out)]
    subprocess.run([*command, "--threads", "2"], check=True)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline", type=Path, required=True)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "speed")
    args = parser.parse_args(argv)
    rows = [
        "# The alignment choice's cost (whole processes)",
        "",
        f"`python tests/benchmarks/bench_align_choice.py --baseline BASE` — {args.rounds} rounds, "
        "alternating order; wall s, median; ratio = this checkout / BASE per round.",
        "",
        "| stack | this checkout s | BASE s | ratio, median [min-max] |",
        "|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory(prefix="align_choice_") as tmp:
        tmp = Path(tmp)
        shape = (480, 640)
        radiance, depth = scenes.edges_scene(shape)
        edge = tmp / "edge"
        scenes.write_stack(edge, radiance, depth, scenes.scene_lens(shape), 8, noisy=True,
                           tolerance=1e-3)  # fmt: skip
        stacks = {
            "motorcycle (lens, 8 frames 370x250)": REPO / "stacks" / "motorcycle",
            "depth edge (lens, 8 frames 640x480, breathing)": edge,
        }
        for name, stack in stacks.items():
            out = tmp / "out.tif"
            run(REPO, stack, out)
            run(args.baseline, stack, out)
            head, base, ratios = [], [], []
            for r in range(args.rounds):
                pair = [(REPO, head), (args.baseline, base)]
                for root, times in pair if r % 2 == 0 else pair[::-1]:
                    times.append(run(root, stack, out))
                ratios.append(head[-1] / base[-1])
            rows.append(
                f"| {name} | {statistics.median(head):.2f} | {statistics.median(base):.2f} | "
                f"{statistics.median(ratios):.2f} [{min(ratios):.2f}-{max(ratios):.2f}] |"
            )
            print(rows[-1], flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "align_choice.md").write_text("\n".join(rows) + "\n", encoding="utf-8")
    print(f"wrote {args.out / 'align_choice.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
