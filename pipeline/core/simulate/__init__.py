"""The forward model (Secs. 3-7): what a flexible-DOF camera captures.

``planner`` decides which effects a scene needs at a tolerance (:func:`plan`),
``render`` renders the plan (:func:`render`, :func:`render_focal_stack`).
"""

from pipeline.core.simulate.planner import (
    EDGE_BLUR_PX,
    MAX_LAYERS,
    MAX_MAGNIFICATION_STEPS,
    REFERENCE_GRID,
    Band,
    Effect,
    Layer,
    Plan,
    Step,
    kernel_error,
    plan,
)
from pipeline.core.simulate.render import render, render_focal_stack

__all__ = [
    "EDGE_BLUR_PX",
    "MAX_LAYERS",
    "MAX_MAGNIFICATION_STEPS",
    "REFERENCE_GRID",
    "Band",
    "Effect",
    "Layer",
    "Plan",
    "Step",
    "kernel_error",
    "plan",
    "render",
    "render_focal_stack",
]
