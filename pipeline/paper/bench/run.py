"""What accuracy costs in time: sweep each accuracy knob, measure error and wall time.

Every knob of the pipeline that trades accuracy for time is swept on scenes with a
ground truth, and each setting's error and time are measured in the same run:

* IPSF (Eqs. 5-7): angular quadrature order of the analytic pixel-area integration,
  time nodes and sub-interval of the numeric Eq. 5, analytic vs numeric, kernel size
  truncation. Error: L1 distance to a converged reference kernel (analytic at order
  :data:`REFERENCE_THETA_ORDER`), mean over depths, on the Sec. 4.1 sweep
  (12.5 mm f/1.4, p(0) = 12.5 mm, 1 mm/s, 0.36 s, 4.65 um pixels).
* Simulation: layer tolerance, occlusion, magnification. Error: RMS difference per
  unit RMS contrast (the tolerance's own meaning, :mod:`pipeline.core.simulate`) against a
  render at :attr:`Config.truth_tolerance`.
* Alignment (Sec. 9): none / analytic / estimated at several matching resolutions.
  Error: corner reprojection error against the true magnification ``p_i / p_ref``, and
  PSNR of the final EDOF image.
* Keeping to the frames (issue 13): the main job as it is, kept to the frames' range (the
  default) or with ``--frame-guard``. Error: PSNR of the final EDOF image.
* Deconvolution (Sec. 4.2): method, iterations, regularisation, kernel variance,
  tile size and overlap, float32 vs float64, kernel truncation. Error: PSNR of the
  final EDOF image against the all-in-focus ground truth.
* Stack sampling: frames over the same depth range. Error: PSNR, and the spread
  (Eq. 8) of the per-depth kernels around the depth-independent one used.

Scenes: the shipped ``stacks/motorcycle`` sample (noisy) and a generated scene with
depth edges (near rectangle, disk, far plane, a slanted floor) rendered as focal
stacks with :func:`pipeline.core.simulate.render.render_focal_stack` at a tight tolerance, noise
free and noisy. Times are the best of :attr:`Config.repeats` runs (cheap calls are
looped until a sample takes ~50 ms).

A default is *dominated* if another setting of the same knob (same scene and metric)
is faster by more than ``time_margin`` and more accurate by a clear margin
(:data:`METRICS`); :func:`dominated_defaults` lists them. Settings that need extra
information (``requires``, e.g. absolute focus positions) are reported apart.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import tifffile

from pipeline.paper.bench.pareto import Config, Row
from pipeline.paper.bench.report import write_plot, write_summary, write_table
from pipeline.paper.bench.scenes import MOTORCYCLE, edges_scene, prepare, scene_lens, write_stack
from pipeline.paper.bench.suites import (
    alignment_rows,
    deconvolution_rows,
    frame_support_rows,
    ipsf_rows,
    sampling_rows,
    simulation_rows,
)

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- driver
def run_accuracy(
    out: Path, *, quick: bool = False, progress: Callable[[str], None] = log.info
) -> list[Row]:
    """Run the benchmark; write accuracy.csv/.md, pareto.png and summary.md into ``out``."""
    config = Config.quick() if quick else Config.full()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    rows: list[Row] = []
    with tempfile.TemporaryDirectory(prefix="flexdof-bench-") as tmp:
        work = Path(tmp)
        radiance, depth = edges_scene(config.shape)
        lens = scene_lens(config.shape)
        progress("IPSF quadrature and truncation")
        rows += ipsf_rows(config)
        progress("simulation: tolerance, occlusion, magnification")
        rows += simulation_rows(config, radiance, depth)
        progress("rendering the edges focal stacks (truth)")
        truth_motorcycle = tifffile.imread(MOTORCYCLE / "ground_truth.tif")
        stacks = {"motorcycle": (MOTORCYCLE, truth_motorcycle)}
        for noisy in (False, True):
            name = "edges-noisy" if noisy else "edges-clean"
            if name in config.deconvolution_scenes:
                directory = write_stack(
                    work / name,
                    radiance,
                    depth,
                    lens,
                    config.frames,
                    noisy=noisy,
                    tolerance=config.truth_tolerance,
                )
                stacks[name] = (directory, radiance)
        prepared = [prepare(name, d, t) for name, (d, t) in stacks.items()]
        progress("alignment")
        rows += alignment_rows(config, [p for p in prepared if p.name != "edges-clean"], work)
        progress("keeping to the frames")
        rows += frame_support_rows(config, prepared, work)
        for prep in prepared:
            progress(f"deconvolution: {prep.name}")
            rows += deconvolution_rows(config, prep)
        progress("stack sampling")
        rows += sampling_rows(config, radiance, depth, work)
    elapsed = time.perf_counter() - start
    write_table(rows, out)
    write_plot(rows, out / "pareto.png")
    write_summary(rows, out / "summary.md", elapsed=elapsed, quick=quick)
    return rows
