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

# "multiframe" restores a focal stack from its frames, per depth (pipeline.core.multiframe):
# only the main job over a focal stack offers it
METHODS = ("wiener", "rl", "sparse", "multiframe")
ALIGN_MODES = ("estimate", "analytic", "none")
# --align-model: the motion an estimated alignment may fit (pipeline.core.align). A focus
# ring's breathing is a scaling about the optical centre, a hand's or a rail's motion a shift
# and a turn: "similarity" fits both with 4 degrees of freedom. "keystone" adds the 2 terms of
# a wide-angle lens turned between frames, "homography" also shear and unequal scaling; on the
# stacks of issue 13 these fit the blur differences instead: rendered breathing stacks' corners
# 0.27-0.35 px from the truth against 0.17-0.21 px; pcb7's, pcb10's and amber's corners
# moving 2.2-12 px (similarity 0.9-5.6 px) when the frames are cropped. "auto" fits the
# similarity, and the keystone where a pair of frames shows a turn's; it is not the default
# because a depth gradient across the frame can look like one
# (tests/benchmarks/results/align/align_models.md). A similarity whose frames all lie within
# a quarter px of one breathing about the image centre is that breathing; "breathing" fits it
# whatever the frames' distance (a camera known not to move; align_breathing.md)
ALIGN_MODELS = ("auto", "similarity", "breathing", "keystone", "affine", "homography")
DEFAULT_MAX_PIXELS = 200_000_000  # 200 Mpx: above any single camera frame; about 8 GB of work


def megapixels(pixels: int) -> str:
    """``pixels`` in Mpx as the size messages print it: three digits under 100 Mpx (0.375,
    12.6), whole Mpx above (256, 4295: no exponent for a decompression bomb's size)."""
    mpx = pixels / 1e6
    return f"{mpx:.3g}" if mpx < 100 else f"{mpx:.0f}"


@dataclasses.dataclass(frozen=True)
class StackOptions:
    """Options of the main job (the ``flexdof stack`` flags)."""

    lens: str | None = None
    method: str = "wiener"
    align: str = "estimate"
    align_model: str = "similarity"
    encoding: str | None = None
    blur_span_px: float | None = None
    tile_px: int = 1024
    align_max_side_px: int = 768
    save_kernel: Path | None = None
    sweep_ends: str = "full"
    max_pixels: int = DEFAULT_MAX_PIXELS  # --max-pixels: refuse larger frames before decoding
    # keep the result to what the aligned frames support (pipeline.core.frame_support):
    # their range, their sharpest frame where it shows more detail, a single frame's noise,
    # twice the fitted blur span. Better on real photographs (issue 13: 6-8/9 regions as
    # good as focus-stack; the default 2-8/9), worse on stacks that follow the paper's model
    # (up to 3.0 dB below the default on synthetic scenes, 4.3 dB with a fitted span) and
    # 17-36% slower: off by default
    frame_guard: bool = False
    # keep the result to the aligned frames (pipeline.core.frame_support, pipeline.jobs.ends):
    # where every frame is flat, the fine band from the average; where an end frame's content
    # lies beyond the focus range, that depth's kernel's correction; the frames' 3x3 range.
    # On the real stacks of issue 13 0/0/0/0 -> 2/8/7/8 of 9 regions as good as focus-stack on
    # every measure; on stacks that follow the model -0.01 to +1.4 dB; 1.04-1.16x the time.
    # False: the paper's linear result as it is
    frame_range: bool = True
    # the value of white in float TIFF frames (--white; None: stack.toml's white, else 1)
    white: float | None = None
    # --match-exposure: each frame divided by its own exposure (pipeline.core.exposure): on
    # rendered stacks whose exposure drifts, within 0.1 dB of one exposure's result where as
    # shot lost up to 0.78 dB; on beetle's flash-lit frames 6/9 regions as good as
    # focus-stack against 9/9 as shot. False: as shot (the exposures measured and reported)
    match_exposure: bool = False
    # --crop: the result cropped to the area every aligned frame covers
    # (pipeline.core.common_area); False: the reference frame's size, with the strips some
    # frame does not reach filled from its edge (the sidecar's common_area says where)
    crop: bool = False

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise InputError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.align not in ALIGN_MODES:
            raise InputError(f"align must be one of {', '.join(ALIGN_MODES)}, got {self.align!r}")
        if self.align_model not in ALIGN_MODELS:
            raise InputError(
                f"align_model (--align-model) must be one of {', '.join(ALIGN_MODELS)}, "
                f"got {self.align_model!r}"
            )
        if self.blur_span_px is not None:
            validate.positive("blur_span_px (--blur-span-px)", self.blur_span_px)
        if self.white is not None:
            validate.positive("white (--white)", self.white)
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
