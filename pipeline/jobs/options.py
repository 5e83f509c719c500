"""The options every job over a stack takes (the ``flexdof stack`` flags), its result
and the progress-callback type.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.core import validate
from pipeline.errors import InputError

METHODS = ("wiener", "rl", "sparse")
ALIGN_MODES = ("estimate", "analytic", "none")
DEFAULT_MAX_PIXELS = 200_000_000  # 200 Mpx: above any single camera frame; about 8 GB of work


@dataclasses.dataclass(frozen=True)
class StackOptions:
    """Options of the main job (the ``flexdof stack`` flags)."""

    lens: str | None = None
    method: str = "wiener"
    align: str = "estimate"
    encoding: str | None = None
    blur_span_px: float | None = None
    tile_px: int = 1024
    align_max_side_px: int = 768
    save_kernel: Path | None = None
    sweep_ends: str = "full"
    max_pixels: int = DEFAULT_MAX_PIXELS  # --max-pixels: refuse larger frames before decoding
    # keep the result to what the aligned frames support (pipeline.core.frame_support):
    # their range, their sharpest frame where it shows more detail, a single frame's noise,
    # twice the fitted blur span. Better on real photographs (issue 13: 0/9 -> 6-8/9
    # regions as good as focus-stack), worse on stacks that follow the paper's model
    # (0.3-1.2 dB on synthetic scenes, 3.8 dB with a fitted span) and 40-80% slower:
    # off by default
    frame_guard: bool = False
    # clip the result to the aligned frames' 3x3 range (pipeline.core.frame_support): no
    # rims or moats on real photographs (issue 13: halo losses to focus-stack 27 -> 0 of
    # 36 regions), never worse than 0.05 dB on stacks that follow the model (+0.1-0.4 dB
    # on the three-plane scenes); --no-frame-range keeps the paper's unclipped result
    frame_range: bool = True

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.align not in ALIGN_MODES:
            raise InputError(f"align must be one of {', '.join(ALIGN_MODES)}, got {self.align!r}")
        if self.blur_span_px is not None:
            validate.positive("blur_span_px", self.blur_span_px)
        validate.whole("max_pixels", self.max_pixels)
        validate.whole("tile_px", self.tile_px)


@dataclasses.dataclass
class StackResult:
    output: Path
    sidecar: dict
    image: np.ndarray


Progress = Callable[[str, int, int], None]


def _no_progress(stage: str, done: int, total: int) -> None:
    """Default progress sink: nothing."""
