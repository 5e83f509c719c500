"""``--method multiframe``: the main job's quality method (issue 13).

The frames are read again and warped onto the reference with Lanczos interpolation (the
average's bilinear warp low-passes each frame, which an average hides and a frame used as
it is does not), then restored per depth from all of them
(:func:`pipeline.core.multiframe.restore`), blended into the Sec. 9 result near depth
changes, at clipped pixels and where the per-frame model does not hold. Holds every frame
and its spectrum in memory: pcb7 (7 frames of 3 Mpx) peaks at 1.2 GiB, pcb10 (10 frames)
at 1.6 GiB, about 3x the default; 7-8x its time
(``tests/benchmarks/results/speed/vs_peer_quality.md``).
"""

from __future__ import annotations

import numpy as np

from pipeline.core import align, multiframe
from pipeline.core.frame_support import FrameSupport, clip_to_frames, quiet_flat_areas
from pipeline.core.stack_kernel import frame_kernels
from pipeline.errors import InputError
from pipeline.io.read import read_frame
from pipeline.jobs.options import Progress, _no_progress


def restore_multiframe(
    aligned,
    blur_span_px: float | None,
    fallback: np.ndarray,
    clipped: np.ndarray | None,
    *,
    average: np.ndarray | None = None,
    support: FrameSupport | None = None,
    progress: Progress = _no_progress,
) -> tuple[np.ndarray, dict]:
    """The multi-frame restoration of an aligned stack
    (:class:`pipeline.jobs.stack.AlignedStack`) with the blur model of its IPSF (the
    lens and absolute positions, else ``blur_span_px``), ``fallback`` the Sec. 9 result.
    Returns the image and what the sidecar records.

    With the main job's frame ``support`` (its ``--frame-range`` steps), the flat areas
    take the ``average``'s fine band as in the default
    (:func:`~pipeline.core.frame_support.quiet_flat_areas`: an in-focus frame's grain is no
    detail) and the result is kept to the frames' range
    (:func:`~pipeline.core.frame_support.clip_to_frames`). That range comes from the
    bilinearly warped frames, which flattens fine peaks: on the ray-traced depth edge it
    costs the multi-frame result 1.0 dB against the range of the Lanczos-warped frames,
    whose overshoot, on beetle, left rims of 0.8-1.1 levels (two more halo losses).
    """
    files = aligned.stack.files
    positions = np.asarray(aligned.positions, dtype=np.float64)
    if np.unique(positions).size < 2:
        raise InputError(
            f"{aligned.stack.base_dir}: --method multiframe restores each depth from frames "
            f"focused at different depths, but all {len(files)} frames have the same focus "
            "position; fix the positions in stack.toml or use --method wiener"
        )
    frames = np.empty((len(files), *np.shape(fallback)), dtype=np.float32)
    for i, (path, a) in enumerate(zip(files, aligned.alignments)):
        frame = read_frame(path, white=aligned.stack.white)
        frames[i] = align.warp(frame, a.homography, aligned.shape, interpolation="lanczos")
        if aligned.gains is not None:  # its exposure (the clipped pixels: the main job's)
            frames[i] /= np.float32(aligned.gains[i])
        progress("multiframe", i + 1, 2 * len(files))

    def kernels_at(x: float, scale: float) -> list[np.ndarray]:
        return frame_kernels(
            positions,
            x,
            lens=aligned.lens,
            absolute=aligned.absolute,
            blur_span_px=blur_span_px,
            scale=scale,
        )

    depths = multiframe.candidate_depths(positions)
    n = len(files)
    image, info = multiframe.restore(
        frames,
        kernels_at,
        depths,
        fallback,
        blocked=clipped,
        progress=lambda done, total: progress("multiframe", n + round(n * done / total), 2 * n),
    )
    if support is not None:
        image, _ = quiet_flat_areas(image, average, support)
        image = clip_to_frames(image, support, clipped)
    info["depths"] = [
        {"position": float(d), "pixels": c} for d, c in zip(depths, info["depths"]) if c
    ]
    return image, info
