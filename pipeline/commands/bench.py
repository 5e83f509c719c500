"""``flexdof bench accuracy``: what accuracy costs in time (table, Pareto plot, summary)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from pipeline.commands import _flags


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="benchmarks: accuracy vs time of every accuracy knob",
        description="Benchmarks of the pipeline itself.",
    )
    kinds = parser.add_subparsers(dest="bench", metavar="BENCH")
    kinds.required = True
    acc = kinds.add_parser(
        "accuracy",
        help="sweep each accuracy knob; error vs ground truth and wall time",
        description=(
            "Sweep the accuracy knobs (IPSF quadrature and size, simulation tolerance/"
            "occlusion/magnification, alignment, deconvolution method/iterations/"
            "regularisation/tiles/precision, frames per stack) on scenes with ground truth; "
            "write accuracy.csv, accuracy.md, pareto.png and summary.md into --output. "
            "The full run takes 10-20 min on 2 cores; --quick about a minute. Needs the "
            "'bench' extra (pip install 'flexdof[bench]')."
        ),
    )
    acc.add_argument("--quick", action="store_true", help="small configuration (CI, < 2 min)")
    acc.add_argument(
        "-o", "--output", "--out", type=Path, default=Path("results/accuracy"),
        help="output folder",
    )
    _flags.add_json(acc)
    acc.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    _flags.require_matplotlib("flexdof bench accuracy")
    import sys

    from pipeline.commands import print_json
    from pipeline.paper import bench

    def progress(stage: str) -> None:
        if not args.quiet:
            print(f"bench: {stage}", file=sys.stderr, flush=True)

    start = time.perf_counter()
    rows = bench.run_accuracy(args.output, quick=args.quick, progress=progress)
    dominated = bench.dominated_defaults(rows)
    seconds = time.perf_counter() - start
    if args.json:
        print_json(
            {
                "measurements": len(rows),
                "seconds": seconds,
                "output": str(args.output),
                "dominated_defaults": [
                    {"knob": d.knob, "scene": d.scene, "default": d.setting, "by": r.setting}
                    for d, r in dominated
                ],
            }
        )
        return 0
    print(
        f"{len(rows)} measurements in {seconds:.0f} s -> {args.output}/"
        "{accuracy.csv, accuracy.md, pareto.png, summary.md}"
    )
    for d, r in dominated:
        print(f"dominated default: {d.knob} ({d.scene}): {d.setting} < {r.setting}")
    return 0
