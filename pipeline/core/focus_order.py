"""The focus order of a focal stack's frames, read from the frames themselves.

Sec. 9 emulates a sweep from frames taken at successive focus steps: their weights, the
IPSF and the stack's end frames (Sec. 4.1) all follow the frames' order. A stack given
without focus positions (a plain folder of frames, the commonest input) is taken in its
files' natural name order, which is the focus order for a focus-bracketing capture, but not
for frames renamed, merged from two runs, shot by hand in any order, or named by a camera
whose counter wrapped (``IMG_9998``, ``IMG_9999``, ``IMG_0001``). A focus stacker that picks
pixels (focus-stack, enfuse) does not care; this pipeline did: shuffled, pcb7, pcb10 and
amber scored 0/9, 5/9 and 3/9 regions as good as focus-stack against 4/9, 8/9 and 8/9 in
order, and score those again now
(``tests/benchmarks/results/real_regions/frame_order.md``).

Frames close in focus look alike: what is sharp in one is nearly as sharp in its
neighbour, and the blur of every depth changes steadily from step to step. Each frame's
*focus map* is the log of its local detail energy (the squared Laplacian of a reduced grey
copy, smoothed); the distance between two frames is the mean absolute difference of their
maps, weighted by how much the focus changes at each pixel across the stack. The focus
order is the path through all frames with the least summed distance between neighbours
(:func:`shortest_path`: a travelling-salesman path, found greedily from a few starts and
improved by 2-opt).

On the four real stacks and the shipped sample the files' order is that path exactly (its
summed distance 1.000 times the shortest); from three random shuffles of each, and from
each rotated as by a wrapped counter, the path recovers the order exactly (the files' order
then costs 1.10-4.3 times the shortest; ``tests/test_focus_order.py``). But the map cannot
tell a step's direction: a plane looks the same one step nearer as one step farther (a
pillbox is a pillbox either side of focus), so a scene of a few planes folds the path (the
rendered three-plane stack, in order, reads 1.5 times a folded path). A changed order is
therefore used only where the magnification confirms it (:func:`focus_order`): focus
breathing rises or falls steadily with focus, and a folded or a handheld stack's scales do
not follow the path. Without breathing (a telecentric lens, rendered stacks) the files'
order stands: name such frames in focus order or give their positions in stack.toml.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from pipeline.core.stack_kernel import MIN_BREATHING, positions_from_scales

MAP_SIDE_PX = 256  # longest side of the reduced frames the focus maps are taken on
MAP_SIGMA_PX = 4.0  # smoothing of the detail energy (px of that copy)
# the files' order is kept unless its summed distance exceeds the shortest path's by this
# factor: in-order stacks read 1.000, shuffled ones 1.5-4.3, a wrapped counter 1.10-1.8
REORDER_RATIO = 1.05
MAX_STARTS = 8  # greedy starts tried (the two frames farthest apart first)
# a changed order is used only where the magnification confirms it: it spans more than
# ``MIN_BREATHING`` and its rank along the new order correlates at least this well
MIN_AGREEMENT = 0.9


def focus_maps(previews: Sequence[np.ndarray]) -> np.ndarray:
    """Log local detail energy of each grey preview, on a copy of ``MAP_SIDE_PX``.

    Each preview is divided by its mean first, so an exposure step between frames does
    not read as a focus change. Returns float32, (n, rows, cols).
    """
    maps = []
    for p in previews:
        g = np.asarray(p, np.float32)
        g = g.mean(axis=2) if g.ndim == 3 else g
        scale = min(1.0, MAP_SIDE_PX / max(g.shape))
        if scale < 1.0:
            g = cv2.resize(g, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        g = g / np.float32(max(float(np.mean(np.abs(g))), 1e-12))
        lap = cv2.Laplacian(g, cv2.CV_32F)
        maps.append(cv2.GaussianBlur(lap * lap, (0, 0), MAP_SIGMA_PX))
    energy = np.stack(maps)
    floor = np.float32(max(1e-3 * float(np.median(energy.max(axis=0))), 1e-30))
    return np.log(energy + floor)


def focus_distances(maps: np.ndarray) -> np.ndarray:
    """Pairwise distance of focus maps: the mean absolute difference, weighted per pixel
    by the range of the maps there (pixels whose focus never changes, flat or beyond
    every frame's reach, say nothing about the order: the weight makes a shuffled real
    stack's order 3-16% longer against the shortest than uniform weights do). Symmetric,
    zero diagonal."""
    n = maps.shape[0]
    weight = (maps.max(axis=0) - maps.min(axis=0)).astype(np.float64)
    total = max(float(weight.sum()), 1e-30)
    flat = maps.reshape(n, -1).astype(np.float64)
    w = weight.ravel()
    d = np.zeros((n, n))
    for i in range(n):
        d[i, i + 1 :] = np.abs(flat[i + 1 :] - flat[i]) @ w / total
    return d + d.T


def path_length(d: np.ndarray, order: Sequence[int]) -> float:
    """Summed distance between neighbours along ``order``."""
    o = np.asarray(order)
    return float(d[o[:-1], o[1:]].sum())


def _two_opt(d: np.ndarray, order: list[int]) -> list[int]:
    """Reverse segments of the open path while that shortens it."""
    n = len(order)
    improved = True
    while improved:
        improved = False
        for i in range(n - 1):
            for j in range(i + 1, n):
                a, b = order[i], order[j]
                before = (d[order[i - 1], a] if i > 0 else 0.0) + (
                    d[b, order[j + 1]] if j + 1 < n else 0.0
                )
                after = (d[order[i - 1], b] if i > 0 else 0.0) + (
                    d[a, order[j + 1]] if j + 1 < n else 0.0
                )
                if after < before - 1e-12:
                    order[i : j + 1] = order[i : j + 1][::-1]
                    improved = True
    return order


def shortest_path(d: np.ndarray) -> list[int]:
    """An open path through every frame with a short summed distance (2-opt local optimum
    from greedy nearest-neighbour paths; the two frames farthest apart are tried as starts
    first, being the likely ends), oriented to start at the lower index of its two ends."""
    n = d.shape[0]
    if n < 3:
        return list(range(n))
    far = np.unravel_index(np.argmax(d), d.shape)
    starts = list(dict.fromkeys([int(far[0]), int(far[1]), *range(n)]))[:MAX_STARTS]
    best, best_len = None, np.inf
    for s in starts:
        order, left = [s], set(range(n)) - {s}
        while left:
            last = order[-1]
            nxt = min(left, key=lambda j: (d[last, j], j))
            order.append(nxt)
            left.remove(nxt)
        order = _two_opt(d, order)
        length = path_length(d, order)
        if length < best_len - 1e-12:
            best, best_len = order, length
    return best if best[0] < best[-1] else best[::-1]


def focus_order(previews: Sequence[np.ndarray], scales: Sequence[float]) -> list[int] | None:
    """The frames' focus order where their files' order is not it, else ``None``.

    Parameters
    ----------
    previews : sequence of ndarray
        Grey (or colour) reduced copies of the frames, in the files' order.
    scales : sequence of float
        Each frame's magnification against the reference, as aligned in that order.

    Returns
    -------
    list of int or None
        Indices into the files' order, nearest focus first or last as the magnification
        rises with the files' order; ``None`` to keep the files' order: fewer than three
        frames, less breathing than ``MIN_BREATHING`` (nothing confirms a changed order), a
        magnification already steady along the files
        (:func:`pipeline.core.stack_kernel.positions_from_scales`), the files' order no
        more than ``REORDER_RATIO`` times the shortest path's length, or a shortest path
        along which the magnification does not rise or fall steadily (rank correlation
        below ``MIN_AGREEMENT``: a scene that folds the path, or a handheld stack whose
        scales are not breathing).
    """
    s = np.asarray(scales, dtype=np.float64)
    n = s.size
    if n < 3 or len(previews) != n or np.ptp(s) <= MIN_BREATHING:
        return None
    if positions_from_scales(s)[1] == "magnification":
        return None
    d = focus_distances(focus_maps(previews))
    path = shortest_path(d)
    if path_length(d, range(n)) < REORDER_RATIO * path_length(d, path):
        return None
    along = s[path]
    agreement = np.corrcoef(np.argsort(np.argsort(along)), np.arange(n))[0, 1]
    if abs(agreement) < MIN_AGREEMENT:
        return None
    return path if agreement > 0 else path[::-1]
