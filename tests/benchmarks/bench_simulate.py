"""Cost of the forward model: plan and render time vs scene and tolerance (not a test).

Run: ``.venv/bin/python tests/benchmarks/bench_simulate.py``. Scenes (250 x 370 px, RGB): a flat
scene (one depth), a 2-plane scene (a near rectangle over a far plane) and the motorcycle
scene of ``stacks/generate_motorcycle.py``; camera: the resampled 12.5 mm f/1.4 lens of
that stack, focused at 750 mm. Then the motorcycle at tolerance 1e-2 / 1e-3 / 1e-4.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "stacks")]

import generate_motorcycle  # noqa: E402

from pipeline.core import optics, simulate  # noqa: E402
from pipeline.core.scene import Camera, Scene  # noqa: E402
from pipeline.errors import InputError  # noqa: E402
from pipeline.io import profiles  # noqa: E402


def timed(scene, camera, tolerance):
    t0 = time.perf_counter()
    plan = simulate.plan(scene, camera, tolerance=tolerance)
    t1 = time.perf_counter()
    simulate.render(scene, camera, plan_=plan)
    t2 = time.perf_counter()
    return plan, t1 - t0, t2 - t1


def main() -> int:
    radiance, depth = generate_motorcycle.scene_arrays()
    rows, cols = depth.shape
    base = profiles.load_lens(generate_motorcycle.LENS)
    lens = dataclasses.replace(
        base,
        pixel_pitch_um=base.width_px * base.pixel_pitch_um / cols,
        width_px=cols,
        height_px=rows,
    )
    camera = Camera.static(lens, optics.image_distance(lens.focal_length_mm, 750.0), 0.1)
    two = np.full(depth.shape, 1800.0)
    two[60:190, 100:270] = 500.0
    scenes = {
        "flat": Scene.from_depth(radiance, np.full(depth.shape, 1000.0)),
        "2-plane": Scene.from_depth(radiance, two),
        "motorcycle": Scene.from_depth(radiance, depth, missing_depth="fill"),
    }
    print(
        f"{'scene':<12}{'tol':>8}{'layers':>8}{'convs':>7}{'occl':>6}{'plan s':>9}{'render s':>10}"
    )
    runs = [(name, 1e-3) for name in scenes] + [("motorcycle", 1e-2), ("motorcycle", 1e-4)]
    for name, tol in runs:
        try:
            plan, tp, tr = timed(scenes[name], camera, tol)
        except InputError as err:  # more layers than simulate.MAX_LAYERS
            print(f"{name:<12}{tol:>8g}  refused: {err}")
            continue
        print(
            f"{name:<12}{tol:>8g}{plan.layer_count:>8}{plan.convolutions:>7}"
            f"{'yes' if plan.occlusion else 'no':>6}{tp:>9.2f}{tr:>10.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
