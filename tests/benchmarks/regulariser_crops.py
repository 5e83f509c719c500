"""Wiener's automatic ``lam`` on scenes no other benchmark uses (issue 13, stop 28).

    python tests/benchmarks/regulariser_crops.py [--noise 0.01 0.02 0.0] [--out FILE]

Six 256 px crops of scikit-image's sample photographs (one of them the three-plane scene of
``synthetic_guard.py``) rendered as nine-frame three-plane stacks (500, 800 and 1600 mm,
frames 450-2500 mm, the engine tests' renderer with the lens's exact PSFs) at each noise
level; per stack the main job's deconvolution alone (``--no-frame-range``, so only the
regulariser differs), the best of a fine ``lam`` grid (29 values, 1e-5..3e-2) on the same
average and kernel, GCV's ``lam`` and noise, and the data's own noise estimate of the average
(``estimate_noise_sigma``). The default should be within 0.3 dB of the best.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
from skimage import data

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

from synthetic_guard import run_job  # noqa: E402
from test_engine import make_stack, positions_for  # noqa: E402

from pipeline.core.colour import srgb_to_linear  # noqa: E402
from pipeline.core.deconvolve.common import estimate_noise_sigma  # noqa: E402
from pipeline.core.quality import psnr  # noqa: E402
from pipeline.core.stack_kernel import wiener_options  # noqa: E402
from pipeline.parallel.scheduler import scheduler_context  # noqa: E402
from pipeline.parallel.tiling import deconvolve_tiled  # noqa: E402

CROPS = {
    "astronaut (synthetic_guard's)": lambda: data.astronaut()[40:296, 130:386],
    "astronaut, lower right": lambda: data.astronaut()[250:506, 200:456],
    "coffee": lambda: data.coffee()[100:356, 200:456],
    "chelsea": lambda: data.chelsea()[30:286, 100:356],
    "rocket": lambda: data.rocket()[100:356, 150:406],
    "immunohistochemistry": lambda: data.immunohistochemistry()[200:456, 200:456],
}
LAMS = np.logspace(-5, -1.5, 29)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, nargs="+", default=[0.01, 0.02, 0.0])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    gcv = importlib.import_module("pipeline.core.deconvolve.gcv")
    found: list[tuple[float, float]] = []
    original = gcv.gcv_regularization

    def spy(y, grid):
        found.append(original(y, grid))
        return found[-1]

    gcv.gcv_regularization = spy
    lines = [
        "| noise | crop | default dB | best dB (lam) | default - best | GCV lam, noise | "
        "the average's noise estimate |",
        "|---|---|---|---|---|---|---|",
    ]
    with scheduler_context(threads=2):
        for noise in args.noise:
            for name, crop in CROPS.items():
                sharp = srgb_to_linear(crop().astype(np.float32) / 255)
                with tempfile.TemporaryDirectory() as tmp:
                    folder = Path(tmp) / "stack"
                    folder.mkdir()
                    make_stack(folder, sharp, [500.0, 800.0, 1600.0], positions_for(450, 2500, 9),
                               noise=noise)
                    found.clear()
                    image, _, seen = run_job(folder, Path(tmp) / "d.tif", frame_range=False)
                    extra = wiener_options(seen["kernel"], seen["samples"])
                    curve = [
                        psnr(deconvolve_tiled(seen["image"], seen["kernel"], method="wiener",
                                              censored=seen["clipped"], regularization=lam,
                                              **extra), sharp)
                        for lam in LAMS
                    ]
                k = int(np.argmax(curve))
                default = psnr(image, sharp)
                gcv_cell = (
                    f"{np.mean([f[0] for f in found]):.1e}, {np.mean([f[1] for f in found]):.4f}"
                    if found else "-"
                )
                estimate = float(np.mean(estimate_noise_sigma(seen["image"])))
                lines.append(
                    f"| {noise} | {name} | {default:.2f} | {curve[k]:.2f} ({LAMS[k]:.1e}) | "
                    f"{default - curve[k]:+.2f} | {gcv_cell} | {estimate:.4f} |"
                )
                print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
