"""The paper's rolling-shutter sensor at full size: plan and render time and peak memory (issue 14).

Sec. 6's tilted DOF was shot on a 2592x1944 rolling-shutter sensor. This renders the Fig. 11
scene (:func:`pipeline.paper.applications.tilted_scene`, a newspaper on a table tilted by
53 deg and a mug) with the constant-speed motion of Eq. 9
(:func:`pipeline.core.motion.plan_tilted_dof`) at that size, through the simulator's plan
and render, and reports the time of each, the plan's size (bands, layers, magnification
steps, FFT convolutions) and the process's peak memory.

    python tests/benchmarks/simulate_paper_sensor.py [--tolerance 1e-2] [--out NAME]
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

from pipeline.core import simulate
from pipeline.core.motion import plan_tilted_dof
from pipeline.core.scene import Camera
from pipeline.io.profiles import load_lens
from pipeline.paper import applications as apps

RESULTS = Path(__file__).resolve().parent / "results" / "simulate_reference"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tolerance", type=float, default=1e-2)
    parser.add_argument("--out", default="paper_sensor", help=f"name of the .json in {RESULTS}")
    args = parser.parse_args(argv)
    lens = load_lens(apps.ROLLING_LENS)
    scene, *_ = apps.tilted_scene(lens)
    motion = plan_tilted_dof(
        lens, apps.TABLE_TILT_DEG, apps.TABLE_THROUGH_MM, exposure_s=apps.TILTED_ROW_EXPOSURE_S
    )
    camera = Camera(lens, motion, row_exposure_s=apps.TILTED_ROW_EXPOSURE_S)
    t0 = time.perf_counter()
    plan = simulate.plan(scene, camera, tolerance=args.tolerance)
    t1 = time.perf_counter()
    image = simulate.render(scene, camera, plan_=plan)
    t2 = time.perf_counter()
    result = {
        "sensor_px": [lens.width_px, lens.height_px],
        "line_time_us": lens.line_time_us,
        "row_exposure_s": apps.TILTED_ROW_EXPOSURE_S,
        "tolerance": args.tolerance,
        "plan_s": round(t1 - t0, 1),
        "render_s": round(t2 - t1, 1),
        "peak_rss_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2),
        "bands": len(plan.bands),
        "layers_max": plan.layer_count,
        "convolutions": plan.convolutions,
        "estimated_error": plan.estimated_error,
        "output_shape": list(image.shape),
        "explain": plan.explain(),
    }
    print(json.dumps(result, indent=1))
    (RESULTS / f"{args.out}.json").write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
