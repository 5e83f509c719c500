"""Probe: the Wiener filter's ``lam`` on a high-ISO stack, scaled by hand (issue 13).

On ``camera_variants.py``'s ``high ISO`` variant of pcb7 (a sensor's shot and read noise
added as at ISO 3200) the default scores 0/9 regions against focus-stack, losing noise in
all nine. This probe runs the main job with the ``lam`` it chooses multiplied by each
factor (by wrapping ``pipeline.core.deconvolve.dispatch._plan_wiener``: a probe, not an
option) and scores each result with the region measures beside focus-stack's result for
the same frames. It also prints what the job chose (the data's noise estimate, GCV's
``lam`` and noise, the final ``lam``) for the variant and its control ``as shot``.

Needs the variants' frames and focus-stack's results, made by

    python tests/benchmarks/camera_variants.py --focus-stack PATH \\
        --variants "as shot,high ISO" --label noise

then ``python tests/benchmarks/high_iso_lam.py [--factors 1,4,16,64]``; writes
``results/real_regions/camera_variants/high_iso_lam.md``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_stack_regions import frames_composite, read_srgb, register, warp
from region_measures import Reference

from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack

HERE = Path(__file__).resolve().parent
VARIANTS = HERE / "results" / "real_regions" / "camera_variants"
HIGH_ISO, AS_SHOT = "pcb7-high-ISO-noise", "pcb7-as-shot-noise"
dispatch = importlib.import_module("pipeline.core.deconvolve.dispatch")
gcv = importlib.import_module("pipeline.core.deconvolve.gcv")


def run(folder: Path, out: Path, factor: float) -> dict:
    """The main job on ``folder`` with its Wiener ``lam`` times ``factor``; what it chose."""
    chosen: dict = {"gcv": []}
    plan, regularization = dispatch._plan_wiener, gcv.gcv_regularization

    def scaled(y, valid, k, sigma, **options):
        params, pad = plan(y, valid, k, sigma, **options)
        chosen.update(sigma=sigma.tolist(), lam=params["lam"].tolist())
        params = {**params, "lam": params["lam"] * factor}
        again = {**options, "regularization": params["lam"]}
        return params, max(pad, plan(y, valid, k, sigma, **again)[1])  # reach of the new lam

    def seen(y, grid):
        found = regularization(y, grid)
        chosen["gcv"].append(found)
        return found

    dispatch._plan_wiener, gcv.gcv_regularization = scaled, seen
    try:
        process_stack(folder, out, StackOptions())
    finally:
        dispatch._plan_wiener, gcv.gcv_regularization = plan, regularization
    return chosen


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--factors", default="1,4,16,64")
    args = parser.parse_args()
    factors = [float(f) for f in args.factors.split(",")]
    frames_dir = VARIANTS / "frames"
    peer = VARIANTS / HIGH_ISO / "work" / f"{HIGH_ISO}_focus-stack.png"
    if not peer.exists():
        sys.exit(f"{peer} is missing: run camera_variants.py first (see this file's docstring)")
    lines = [
        "# The Wiener filter's lam on a high-ISO stack (issue 13)",
        "",
        "`python tests/benchmarks/high_iso_lam.py`: what the main job chose, then its",
        "result with that lam times each factor, by region (3x3) beside focus-stack's.",
        "",
        "| stack | data's noise (R, G, B) | GCV lam / noise (R, G, B) | lam used |",
        "|---|---|---|---|",
    ]
    with tempfile.TemporaryDirectory(prefix="high_iso_lam_") as tmp:
        results = {}
        for name in (AS_SHOT, HIGH_ISO):
            for factor in factors if name == HIGH_ISO else [1.0]:
                out = Path(tmp) / f"{name}_{factor:g}.tif"
                chosen = run(frames_dir / name, out, factor)
                if factor == 1.0:
                    cells = ", ".join(f"{lam:.2g} / {noise:.2g}" for lam, noise in chosen["gcv"])
                    sigma = ", ".join(f"{s:.2g}" for s in chosen["sigma"])
                    lines.append(f"| {name} | {sigma} | {cells} | {chosen['lam'][0]:.3g} |")
                if name == HIGH_ISO:
                    results[f"lam x {factor:g}"] = out
        side = json.loads(Path(f"{results['lam x 1']}.json").read_text())
        first = read_srgb(results["lam x 1"])
        shape = first.shape[:2]
        frames, valid = [], np.ones(shape, bool)
        for meta, path in zip(side["frames"], side["inputs"]):
            frame, cover = warp(read_srgb(Path(path)), np.array(meta["homography"]), shape)
            frames.append(frame)
            valid &= cover
        images = {label: read_srgb(path) for label, path in results.items()}
        h, _ = register(read_srgb(peer), frames_composite(frames))
        images["focus-stack"], cover = warp(read_srgb(peer), h, shape)
        valid &= cover
        reference = Reference(frames, valid)
        scores = {label: reference.measure(image) for label, image in images.items()}
    for measure, unit in (("sharpness", "px"), ("noise", "levels"), ("haze", "fraction")):
        lines += ["", f"**{measure}** ({unit}), regions top-left to bottom-right", ""]
        lines += ["| result | " + " | ".join(str(i) for i in range(1, 10)) + " |"]
        lines += ["|---|" + "---|" * 9]
        for label, score in scores.items():
            digits = 3 if measure == "haze" else 2
            values = " | ".join(f"{v:.{digits}f}" for v in score[measure])
            lines.append(f"| {label} | {values} |")
    text = "\n".join(lines) + "\n"
    print(text)
    (VARIANTS / "high_iso_lam.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
