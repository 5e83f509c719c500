"""``flexdof bench accuracy``: what accuracy costs in time (table, Pareto plot, summary)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


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
            "write accuracy.csv, accuracy.md, pareto.png and summary.md into --out. "
            "The full run takes 10-20 min on 2 cores; --quick about a minute."
        ),
    )
    acc.add_argument("--quick", action="store_true", help="small configuration (CI, < 2 min)")
    acc.add_argument("--out", type=Path, default=Path("results/accuracy"), help="output folder")
    acc.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.paper import bench

    start = time.perf_counter()
    rows = bench.run_accuracy(
        args.out, quick=args.quick, progress=lambda stage: print(f"bench: {stage}", flush=True)
    )
    dominated = bench.dominated_defaults(rows)
    print(
        f"{len(rows)} measurements in {time.perf_counter() - start:.0f} s -> {args.out}/"
        "{accuracy.csv, accuracy.md, pareto.png, summary.md}"
    )
    for d, r in dominated:
        print(f"dominated default: {d.knob} ({d.scene}): {d.setting} < {r.setting}")
    return 0
