"""``flexdof bench accuracy``: what accuracy costs in time, for every knob.

``scenes`` builds the scenes with ground truth, ``suites`` measures each knob,
``pareto`` finds the front and the dominated defaults, ``report`` writes the
table, plot and summary, and ``run`` drives it all (:func:`run_accuracy`).
"""

from pipeline.paper.bench.pareto import (
    METRICS,
    Config,
    Metric,
    Row,
    clearly_better,
    default_of,
    dominated_defaults,
    oriented,
    pareto_front,
)
from pipeline.paper.bench.report import read_table, write_plot, write_summary, write_table
from pipeline.paper.bench.run import run_accuracy
from pipeline.paper.bench.scenes import Prepared, edges_scene, prepare, scene_lens, write_stack
from pipeline.paper.bench.suites import (
    alignment_rows,
    deconvolution_rows,
    frame_support_rows,
    ipsf_rows,
    sampling_rows,
    simulation_rows,
)
from pipeline.paper.bench.timing import best_times

__all__ = [
    "METRICS",
    "Config",
    "Metric",
    "Prepared",
    "Row",
    "alignment_rows",
    "best_times",
    "clearly_better",
    "deconvolution_rows",
    "default_of",
    "dominated_defaults",
    "edges_scene",
    "frame_support_rows",
    "ipsf_rows",
    "oriented",
    "pareto_front",
    "prepare",
    "read_table",
    "run_accuracy",
    "sampling_rows",
    "scene_lens",
    "simulation_rows",
    "write_plot",
    "write_stack",
    "write_summary",
    "write_table",
]
