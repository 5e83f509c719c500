"""``flexdof figures``: the paper's simulated Figs. 3, 5 and 9 as PNG, CSV and Markdown."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "figures",
        help="reproduce the paper's simulated figures (Figs. 3, 5, 9)",
        description="Write Fig. 3 (PSF vs IPSF profiles), Fig. 5 (Eq. 8 dissimilarity "
        "matrices) and Fig. 9 (MTFs of k1, k2 and the table of effective noise and DOF, "
        "by Wiener deconvolution of a natural image) into --out.",
    )
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument(
        "--only", action="append", choices=("3", "5", "9"), help="figure to make (repeatable)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline import figures

    written = figures.render_figures(args.out, which=args.only or figures.FIGURES)
    for path in written:
        print(path)
    return 0
