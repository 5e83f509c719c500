"""``flexdof sample-path``: where the shipped sample stack and lens profiles are.

In a checkout they are ``stacks/motorcycle`` and ``lens_profiles/``; a wheel carries
them inside the package, so ``flexdof stack "$(flexdof sample-path)" -o edof.tif`` runs
the main job on the sample from any folder.
"""

from __future__ import annotations

import argparse

from pipeline.commands import _flags


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sample-path",
        help="print the folder of the shipped sample stack (or of the lens profiles)",
        description="Print where the shipped sample focal stack lives (a folder with "
        "stack.toml, eight frames, the ground truth and a depth map), e.g. "
        'flexdof stack "$(flexdof sample-path)" -o edof.tif',
    )
    parser.add_argument(
        "--lens-profiles",
        action="store_true",
        help="print the folder of the shipped lens profiles instead",
    )
    _flags.add_json(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pipeline.commands import print_json
    from pipeline.io.profiles import available_lenses, shipped

    if args.json:
        print_json(
            {
                "sample": str(shipped("sample")),
                "lens_profiles": str(shipped("lens_profiles")),
                "lenses": available_lenses(),
            }
        )
    else:
        print(shipped("lens_profiles" if args.lens_profiles else "sample"))
    return 0
