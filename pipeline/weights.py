"""Frame weights that turn a focal stack into a flexible-DOF capture (Sec. 9, Sec. 5-7).

A detector moving at constant speed over ``[p_min, p_max]`` spends equal time
per unit of image distance. A focal stack samples that sweep at its frames'
positions ``p_i``; giving each frame the length of the interval of ``p`` it
stands for (half-way to each neighbour, clipped to the swept range) makes the
weighted average emulate the sweep (Sec. 9).
"""

from __future__ import annotations

import numpy as np

from pipeline.errors import InputError


def constant_speed_weights(image_distances_mm) -> np.ndarray:
    """Weights (sum 1) that emulate a constant-speed sweep over the frames' range (Sec. 9).

    Parameters
    ----------
    image_distances_mm : array_like, shape (n,)
        Each frame's focus position (image distance, or any coordinate linear in
        it); any order, non-uniform spacing and duplicates allowed.

    Returns
    -------
    ndarray, shape (n,)
        ``w_i`` proportional to the length of ``p`` nearer to ``p_i`` than to any
        other frame, within ``[p_min, p_max]``; frames at the same position share
        their interval equally. A single frame, or all frames at one position,
        get equal weights.
    """
    p = np.asarray(image_distances_mm, dtype=np.float64).ravel()
    if p.size == 0:
        raise InputError("image_distances_mm is empty: a stack needs at least one frame")
    if not np.all(np.isfinite(p)):
        raise InputError(f"image_distances_mm must be finite, got {p.tolist()}")
    unique, inverse, counts = np.unique(p, return_inverse=True, return_counts=True)
    if unique.size == 1:
        return np.full(p.size, 1.0 / p.size)
    midpoints = 0.5 * (unique[1:] + unique[:-1])
    lower = np.concatenate(([unique[0]], midpoints))
    upper = np.concatenate((midpoints, [unique[-1]]))
    cell = (upper - lower) / (unique[-1] - unique[0])
    return cell[inverse] / counts[inverse]
