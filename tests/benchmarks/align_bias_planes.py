"""ECC's alignment bias on a focal stack without breathing whose frames differ strongly in
blur (issue 13).

    python tests/benchmarks/align_bias_planes.py [--out tests/benchmarks/results/align]

The engine tests' three-plane stack (:func:`test_engine.make_stack`: a 256 px astronaut crop
split by columns into planes at 500, 800 and 1600 mm, exact lens PSFs, no magnification
change, so the true alignment is the identity), 5 and 9 frames focused from 450 to 2500 mm.
Reports the PSNR of ``flexdof stack`` with ``--align none`` and with the default estimate,
and the estimate's per-frame scale and largest corner displacement (px).
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
from skimage import data

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

from benchmarks.align_without_breathing import corner_error_px, write_table  # noqa: E402
from test_engine import make_stack, positions_for  # noqa: E402

from pipeline.core.colour import srgb_to_linear  # noqa: E402
from pipeline.core.quality import psnr  # noqa: E402
from pipeline.jobs.options import StackOptions  # noqa: E402
from pipeline.jobs.stack import process_stack  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "align")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # the lens profile's sensor is larger than the frames
    sharp = srgb_to_linear(data.astronaut()[40:296, 130:386].astype(np.float32) / 255)
    rows = [
        "# ECC's bias on a three-plane stack without breathing (issue 13)",
        "",
        "`python tests/benchmarks/align_bias_planes.py`: PSNR (dB) against the truth; the "
        "estimate's scales (frame to reference) and largest corner displacement (px, 256 px "
        "frames). The true alignment is the identity.",
        "",
        "| frames | --align none | estimate | estimated scales | corner px |",
        "|---|---|---|---|---|",
    ]
    for n in (5, 9):
        with tempfile.TemporaryDirectory(prefix="align_bias_") as tmp:
            folder = Path(tmp) / "stack"
            folder.mkdir()
            make_stack(folder, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, n))
            none = process_stack(folder, Path(tmp) / "n.tif", StackOptions(align="none"))
            est = process_stack(folder, Path(tmp) / "e.tif", StackOptions())
            frames = est.sidecar["frames"]
            scales = ", ".join(f"{f['scale']:.4f}" for f in frames)
            corner = corner_error_px([f["homography"] for f in frames], sharp.shape[:2])
            rows.append(
                f"| {n} | {psnr(none.image, sharp):.2f} | {psnr(est.image, sharp):.2f} | "
                f"{scales} | {corner:.2f} |"
            )
            print(rows[-1], flush=True)
    write_table(args.out / "align_bias_planes.md", rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
