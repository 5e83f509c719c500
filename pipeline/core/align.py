"""Magnification (focus-breathing) compensation with homographies (Sec. 3, 9).

Moving the detector (or the lens, Sec. 8) to change focus changes the
magnification ``p/u`` of the imaging system (Sec. 3, footnote 1; Fig. 2's last
column), so the frames of a focal stack do not overlay. Sec. 9 averages the
frames "compensating for magnification effects if possible": this module
estimates, for every frame, a homography ``H`` that maps the frame's full-
resolution pixel coordinates to the reference frame's, and warps frames with it.

Conventions
-----------
Pixel coordinates are OpenCV's: ``(x, y) = (column, row)`` with pixel centres at
integer coordinates. A homography maps homogeneous column vectors,
``[x', y', w']^T = H [x, y, 1]^T``, and is stored normalised to ``H[2, 2] = 1``.
``Alignment.scale`` is the frame's magnification relative to the reference,
``p_i / p_ref`` for a detector-moving focus, i.e. ``1 / scale_of(H, centre)`` (read at
the image centre).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.errors import InputError

logger = logging.getLogger(__name__)

__all__ = [
    "Alignment",
    "analytic_alignment",
    "breathing_about_centre",
    "compose",
    "estimate_alignment",
    "map_points",
    "rescale_homography",
    "scale_of",
    "warp",
]

# The ECC motion each model is fitted as, then projected onto the model (``_project``).
# "auto" is not a motion: a similarity, or a keystone for the whole stack (``_turn_found``).
_MODELS = {
    "homography": cv2.MOTION_HOMOGRAPHY,
    "affine": cv2.MOTION_AFFINE,
    "similarity": cv2.MOTION_AFFINE,  # ECC has no similarity model: fit affine, then project
    "keystone": cv2.MOTION_HOMOGRAPHY,  # a similarity and the two terms of a turn's keystone
    "breathing": cv2.MOTION_AFFINE,  # fitted as a similarity, then as the stack's breathing
}
AUTO_MODEL = "auto"
_PERSPECTIVE_MODELS = ("homography", "keystone")
# "auto" fits the keystone for the whole stack where one neighbour pair shows a turn
# (``_turn_found``): refining its similarity as a keystone takes away this share of its
# decorrelation (1 - ECC correlation, half resolution) and moves a corner by this many px of
# the matching copy, and the perspective row fitted on each half of the frame (left and
# right, top and bottom) is the whole frame's: the halves' fits differ by at most this many
# times the whole fit's row. pcb7's copies seen through a 16 mm lens on APS-C turned by up to
# 0.25-1 degree (with shifts of up to 1% or not): a pair with shares of 0.11-0.67, corners of
# 1.06-6.4 px and halves 0.11-1.27 apart. Stacks not turned whose blur differences pass the
# share and the corner (pcb10 cropped by 20%, amber cropped by 16% or halved): halves 6.1-9.2
# apart (tests/benchmarks/align_models.py). A depth gradient across the frame can pass all
# three, which is why "auto" is not the default (see estimate_alignment)
_TURN_SHARE = 0.05
_TURN_CORNER_PX = 0.5
_TURN_SPREAD = 2.5
_METHODS = ("auto", "ecc", "features")
_INTERPOLATIONS = {
    "linear": cv2.INTER_LINEAR,
    "cubic": cv2.INTER_CUBIC,
    "lanczos": cv2.INTER_LANCZOS4,
}
_SCALE_RANGE = (0.5, 2.0)  # plausible magnification between two frames of one stack
_MAX_PERSPECTIVE = 0.05  # max |w - 1| of the homogeneous coordinate over the image
_COARSEST_SIDE_PX = 96  # the pyramid stops before its shorter side drops below this
# "auto" also tries features where ECC's best correlation is below this: neighbours of the
# real stacks correlate at 0.98-1.0, while a 3-degree turn and a 6% shift by hand left ECC
# in a false optimum at 0.75 (pcb7, a frame 0.55% off in scale; features + ECC: 0.99)
_CONFIDENT_CORRELATION = 0.9
_ECC_GAUSS_SIZE = 5
_FEATURES_MAX = 4000
# A similarity per frame is snapped to the stack's breathing about the image centre
# (:func:`breathing_about_centre`) where every frame's lies within this many px of the
# matching copy from it: what is left is the estimate's error, not motion. ECC's peak moves
# with the frames' blur differences: on rendered breathing stacks (a scaling about the
# centre and nothing else) the similarities lie 0.14-0.16 px from it, with corners 0.17-0.21
# px from the truth, the breathing's 0.07 px; the real stacks' frames move: beetle's lie
# up to 0.46 px from it, amber's 2.2, pcb7's 3.9, pcb10's 9.7
# (tests/benchmarks/results/align/align_breathing.md)
BREATHING_TOLERANCE_PX = 0.25


@dataclass(frozen=True, eq=False)
class Alignment:
    """The transform of one frame onto the reference frame.

    Attributes
    ----------
    homography : ndarray, shape (3, 3), float64
        Maps the frame's full-resolution pixel coordinates to the reference's
        (``H[2, 2] = 1``); pass it to :func:`warp`.
    scale : float
        The frame's magnification relative to the reference at the image centre,
        ``1 / scale_of(H, centre)``
        (``p_i / p_ref`` for a detector-moving focus, Fig. 1).
    method : str
        ``"reference"``, ``"ecc"``, ``"features"``, ``"features+ecc"``, ``"analytic"``
        or ``"fallback"``.
    ok : bool
        False when the estimate failed and ``homography`` is a fallback.
    message : str
        Why the estimate failed (empty when ``ok``).
    correlation : float or None
        ECC correlation coefficient of the frame with its anchor on their overlap
        at the matching resolution (None when not measured).
    model : str or None
        The motion model the estimate fitted (what ``model="auto"`` chose; "breathing"
        where the similarities were snapped to the stack's breathing); None
        where nothing was estimated (analytic or identity transforms).
    """

    homography: np.ndarray
    scale: float
    method: str
    ok: bool = True
    message: str = ""
    correlation: float | None = None
    model: str | None = None


class _EstimationError(Exception):
    """An estimate failed; the message says why (turned into ``Alignment.message``)."""


# --- homography helpers -------------------------------------------------------------------------


def _as_homography(h: np.ndarray, name: str = "homography") -> np.ndarray:
    """Validate ``h`` and return it as float64 3x3 normalised to ``h[2, 2] = 1``."""
    m = np.asarray(h, dtype=np.float64)
    if m.shape == (2, 3):
        m = np.vstack([m, [0.0, 0.0, 1.0]])
    if m.shape != (3, 3):
        raise InputError(f"{name} must be a 3x3 (or 2x3 affine) matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)) or m[2, 2] == 0.0:
        raise InputError(f"{name} must be finite with h[2, 2] != 0, got {m.tolist()}")
    m = m / m[2, 2]
    if abs(np.linalg.det(m)) < 1e-12:
        raise InputError(f"{name} is singular (det ~ 0): {m.tolist()}")
    return m


def scale_of(h: np.ndarray, at: tuple[float, float] | None = None) -> float:
    """Linear scale factor of the map ``h``: ``sqrt(|det J|)`` of its Jacobian ``J``.

    Without ``at``, ``J = h[:2, :2]`` (``h[2, 2] = 1``): the map's scale everywhere when
    it is affine (a similarity, an affine); with perspective terms it is no point's scale.
    With ``at = (x, y)``, the Jacobian at that point, ``J = (h[:2, :2] - h(x)
    h[2, :2]) / w`` with ``w = h[2, :2] . x + 1``: a keystone magnifies one side of the
    frame more than the other, so a turned frame's magnification is read at the image
    centre. (Read from ``h[:2, :2]``, pcb7's frames turned by up to 0.5 degree as through a
    16 mm lens read scales out of their focus order, 1.0113, 1.0063, 1.0068, 1.0, 0.978,
    and the sweep weights were lost; at the centre they read 1.0216, 1.0109, 1.0059, 1.0,
    0.9923, within 0.0002 of the frames not turned.)

    For a pure scaling by ``s`` about any point this is ``s``. The magnification
    of a frame relative to the reference is ``1 / scale_of(alignment.homography, centre)``.
    """
    m = _as_homography(h)
    jacobian = m[:2, :2]
    if at is not None:
        x = np.array([at[0], at[1], 1.0])
        w = float(m[2] @ x)
        if not w > 0:
            raise InputError(
                f"the homography sends the point {tuple(at)} to infinity or behind the camera "
                f"(w = {w:.3g}); its scale there is undefined: {m.tolist()}"
            )
        mapped = (m[:2] @ x) / w
        jacobian = (m[:2, :2] - np.outer(mapped, m[2, :2])) / w
    return float(math.sqrt(abs(np.linalg.det(jacobian))))


def compose(*homographies: np.ndarray) -> np.ndarray:
    """Product ``h1 @ h2 @ ... @ hn`` (``hn`` applied first), normalised to ``[2, 2] = 1``.

    ``compose(h_j, h_ij)`` maps frame i to the reference when ``h_ij`` maps
    frame i to frame j and ``h_j`` maps frame j to the reference.
    """
    if not homographies:
        raise InputError("compose needs at least one homography, got none")
    out = np.eye(3)
    for k, h in enumerate(homographies):
        out = out @ _as_homography(h, f"homographies[{k}]")
    return out / out[2, 2]


def map_points(h: np.ndarray, points_xy: np.ndarray) -> np.ndarray:
    """Apply ``h`` to points of shape (..., 2) given as (x, y); returns float64 (..., 2)."""
    m = _as_homography(h)
    p = np.asarray(points_xy, dtype=np.float64)
    if p.shape[-1:] != (2,):
        raise InputError(f"points_xy must have shape (..., 2), got {p.shape}")
    q = p @ m[:, :2].T + m[:, 2]
    return q[..., :2] / q[..., 2:]


def breathing_about_centre(
    homographies: Sequence[np.ndarray], shape: tuple[int, int]
) -> tuple[list[np.ndarray], np.ndarray]:
    """The stack's focus breathing alone: per frame, the scaling about the image centre
    nearest its homography.

    A focus ring (or a moving detector, Sec. 3) on a camera that does not move changes
    only the magnification ``p/u`` about the optical axis (Fig. 1), taken as the image
    centre ``c``: ``x -> c + s_k (x - c)``. ``s_k`` is the least-squares fit over a grid
    of the frame's points ``q``, ``s = sum (q - c) . (H q - c) / sum |q - c|^2``.

    Parameters
    ----------
    homographies : sequence of (3, 3) arrays
        Each frame's map onto the reference, in the pixel coordinates of ``shape``.
    shape : (rows, cols)

    Returns
    -------
    models : list of (3, 3) arrays
        The scaling about the centre per frame.
    distances : ndarray (frames,)
        The largest distance (px) over the image between each homography's map and its
        model's. Both are affine for a similarity, so it is reached at a corner; for a
        homography the grid bounds it from below.
    """
    rows, cols = shape[:2]
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2])
    ys, xs = np.mgrid[0 : rows - 1 : 9j, 0 : cols - 1 : 9j]
    grid = np.stack([xs.ravel(), ys.ravel()], axis=1)
    offsets = grid - centre
    models, distances = [], []
    spread = float(np.sum(offsets * offsets))  # 0 for a single pixel: no scale is seen
    for h in homographies:
        mapped = map_points(h, grid)
        s = float(np.sum(offsets * (mapped - centre))) / spread if spread > 0 else 1.0
        model = np.array([[s, 0, (1 - s) * centre[0]], [0, s, (1 - s) * centre[1]], [0, 0, 1.0]])
        models.append(model)
        distances.append(float(np.hypot(*(mapped - map_points(model, grid)).T).max()))
    return models, np.array(distances)


def _scaling(from_shape: tuple[int, int], to_shape: tuple[int, int]) -> np.ndarray:
    """Map pixel coordinates of an image to those of its resized copy (cv2.resize's geometry).

    A resize by ``s = to / from`` maps pixel *edges* ``x + 1/2`` to ``s (x + 1/2)``; with
    pixel centres at integers, ``x' = s (x + 1/2) - 1/2``.
    """
    sy = to_shape[0] / from_shape[0]
    sx = to_shape[1] / from_shape[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def rescale_homography(
    h: np.ndarray, from_shape: tuple[int, int], to_shape: tuple[int, int]
) -> np.ndarray:
    """Express ``h`` (acting on pixels of ``from_shape`` images) on ``to_shape`` pixels."""
    s = _scaling(from_shape, to_shape)
    out = s @ h @ np.linalg.inv(s)
    return out / out[2, 2]


def _implausible(h: np.ndarray, shape: tuple[int, int]) -> str:
    """Why ``h`` cannot be a focus-breathing transform of a ``shape`` frame ('' if plausible)."""
    if not np.all(np.isfinite(h)):
        return "non-finite homography"
    m = h / h[2, 2]
    det = float(np.linalg.det(m[:2, :2]))
    if det <= 0:
        return f"degenerate or mirroring homography (det of linear part {det:.3g})"
    s = math.sqrt(det)
    if not _SCALE_RANGE[0] <= s <= _SCALE_RANGE[1]:
        return f"implausible scale {s:.3f} (outside {_SCALE_RANGE[0]}..{_SCALE_RANGE[1]})"
    rows, cols = shape
    corners = np.array([[0, 0], [cols - 1, 0], [0, rows - 1], [cols - 1, rows - 1]], float)
    w = corners @ m[2, :2] + 1.0
    if np.max(np.abs(w - 1.0)) > _MAX_PERSPECTIVE:
        return f"strong perspective terms (|w - 1| up to {np.max(np.abs(w - 1.0)):.3f})"
    return ""


# --- matching images ----------------------------------------------------------------------------


def _checked_frame(frame, name: str) -> np.ndarray:
    """``frame`` as an array, or an InputError naming it when it cannot be an image."""
    a = np.asarray(frame)
    if a.ndim not in (2, 3) or a.size == 0 or not np.issubdtype(a.dtype, np.number):
        raise InputError(
            f"{name} must be a non-empty numeric (rows, cols) or (rows, cols, channels) "
            f"array, got shape {a.shape} dtype {a.dtype}"
        )
    if np.iscomplexobj(a):
        raise InputError(f"{name} must be real-valued, got dtype {a.dtype}")
    return a


def _load(frame: np.ndarray | Callable[[], np.ndarray], index: int) -> np.ndarray:
    return _checked_frame(frame() if callable(frame) else frame, f"frames[{index}]")


def _grey(a: np.ndarray) -> np.ndarray:
    x = a.astype(np.float32, copy=False)
    if x.ndim == 2:
        return x
    if x.shape[2] == 3:
        return cv2.cvtColor(np.ascontiguousarray(x), cv2.COLOR_RGB2GRAY)
    return x.mean(axis=2, dtype=np.float32)


def _matching_image(a: np.ndarray, max_side_px: int) -> np.ndarray:
    """Reduced grey copy of a frame for matching, still in linear light.

    Defocus is a convolution in linear light (Eqs. 3-5), so a sharp frame and a
    defocused one correlate best at the true alignment only while both stay
    linear: a gamma or log encoding, or a division by the local contrast, moves
    the apparent position of blurred edges and biases the estimated scale (so
    does any filter fixed in pixels, such as a local-mean high-pass, because the
    frames differ in scale). ECC's correlation is invariant to a global gain and
    offset, so no photometric normalisation is needed.
    """
    g = _grey(a)
    rows, cols = g.shape
    s = max_side_px / max(rows, cols)
    if s < 1:
        size = (max(round(cols * s), 1), max(round(rows * s), 1))
        g = cv2.resize(g, size, interpolation=cv2.INTER_AREA)
    return g


def _pyramid(img: np.ndarray) -> list[np.ndarray]:
    """Coarse-to-fine list of ``img`` halved (cv2.resize, INTER_AREA) down to ~96 px."""
    levels = [img]
    while min(levels[-1].shape) // 2 >= _COARSEST_SIDE_PX:
        top = levels[-1]
        size = (top.shape[1] // 2, top.shape[0] // 2)
        levels.append(cv2.resize(top, size, interpolation=cv2.INTER_AREA))
    return levels[::-1]


def _is_textureless(img: np.ndarray) -> bool:
    """Constant up to rounding (relative to the level; noise is caught by the correlation)."""
    return float(np.std(img)) <= 1e-5 * float(np.mean(np.abs(img)))


# --- estimators (reduced resolution, template -> input coordinates) ----------------------------


def _project(w: np.ndarray, model: str, shape: tuple[int, int]) -> np.ndarray:
    """Constrain a 3x3 warp to ``model``.

    Similarity: the rotation+scaling nearest (Frobenius norm) to the linear
    part, with the translation chosen so the image centre maps as before.

    Keystone: in coordinates centred on the image, ``m = S P`` with ``P`` the
    perspective row alone (``[[1, 0, 0], [0, 1, 0], [p1, p2, 1]]``) and ``S``
    affine; ``S`` is projected onto a similarity as above. A camera turned by
    ``theta`` about an axis through its lens is ``K R K^-1``: in centred
    coordinates its ``S`` is a similarity up to a scaling of one axis by
    ``cos(theta)`` (1.5e-4 at 1 degree), so this model holds focus breathing, a
    shift, a roll and a turn's keystone with 6 degrees of freedom, without the
    homography's shear and unequal scaling, which fit blur differences.
    """
    m = w / w[2, 2]
    if model == "homography":
        return m
    if model == "keystone":
        c = _centring(shape)
        centred = np.linalg.inv(c) @ m @ c
        centred = centred / centred[2, 2]
        p = np.eye(3)
        p[2, :2] = centred[2, :2]
        s = centred @ np.linalg.inv(p)
        out = c @ _project(s / s[2, 2], "similarity", (1, 1)) @ p @ np.linalg.inv(c)
        return out / out[2, 2]
    out = np.eye(3)
    out[:2] = m[:2]
    if model == "similarity":
        a = 0.5 * (out[0, 0] + out[1, 1])
        b = 0.5 * (out[1, 0] - out[0, 1])
        centre = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
        target = out[:2, :2] @ centre + out[:2, 2]
        out[:2, :2] = [[a, -b], [b, a]]
        out[:2, 2] = target - out[:2, :2] @ centre
    return out


def _ecc(
    template: list[np.ndarray],
    image: list[np.ndarray],
    init: np.ndarray,
    model: str,
    start_level: int = 0,
) -> tuple[np.ndarray, float]:
    """Coarse-to-fine ECC (OpenCV ``findTransformECC``) from ``init`` (finest-level coords).

    Returns the warp (template pixel coords -> image pixel coords at the finest
    level) and the final correlation coefficient.
    """
    finest = template[-1].shape
    w = rescale_homography(init, finest, template[start_level].shape)
    cc = -1.0
    for level in range(start_level, len(template)):
        t, m = template[level], image[level]
        if level > start_level:
            w = rescale_homography(w, template[level - 1].shape, t.shape)
        iterations = 100 if level == 0 else (12 if level == len(template) - 1 else 30)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, iterations, 1e-5)
        warp32 = (w if model in _PERSPECTIVE_MODELS else w[:2]).astype(np.float32)
        try:
            cc, warp32 = cv2.findTransformECC(
                t, m, warp32, _MODELS[model], criteria, None, _ECC_GAUSS_SIZE
            )
        except cv2.error as err:
            raise _EstimationError(f"ECC failed at pyramid level {level}: {err.err}") from err
        w = np.eye(3)
        w[: warp32.shape[0]] = warp32
        w = _project(w, model, t.shape)
    return w, float(cc)


def _features(img: np.ndarray) -> tuple[list, np.ndarray | None]:
    """SIFT keypoints and descriptors of a matching image, 0.5..99.5th percentile as 0..255."""
    lo, hi = np.percentile(img, [0.5, 99.5])
    gain = 255.0 / max(hi - lo, 1e-12)
    u8 = cv2.convertScaleAbs(np.maximum(img, lo), alpha=gain, beta=-lo * gain)  # |x|: floor
    sift = cv2.SIFT_create(nfeatures=_FEATURES_MAX)
    return sift.detectAndCompute(u8, None)


def _feature_warp(fa: tuple, fb: tuple, model: str) -> np.ndarray:
    """RANSAC fit (template a -> image b) to ratio-tested SIFT matches."""
    (ka, da), (kb, db) = fa, fb
    if da is None or db is None or len(ka) < 8 or len(kb) < 8:
        raise _EstimationError("too few features (low texture)")
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.75 * p[1].distance]
    if len(good) < 8:
        raise _EstimationError(f"too few feature matches ({len(good)})")
    src = np.float32([ka[g.queryIdx].pt for g in good])
    dst = np.float32([kb[g.trainIdx].pt for g in good])
    try:
        if model in _PERSPECTIVE_MODELS:
            h, inliers = cv2.findHomography(src, dst, cv2.RANSAC, 1.5)
        elif model == "affine":
            h, inliers = cv2.estimateAffine2D(src, dst, ransacReprojThreshold=1.5)
        else:
            h, inliers = cv2.estimateAffinePartial2D(src, dst, ransacReprojThreshold=1.5)
    except cv2.error as err:
        raise _EstimationError(f"RANSAC failed: {err.err}") from err
    if h is None or inliers is None or int(inliers.sum()) < 8:
        raise _EstimationError("RANSAC found no consistent transform")
    w = np.eye(3)
    w[: h.shape[0]] = h
    return w / w[2, 2]


def _correlation(template: np.ndarray, image: np.ndarray, w: np.ndarray) -> float:
    """ECC correlation of ``template`` with ``image`` warped by ``w`` on their overlap."""
    size = (template.shape[1], template.shape[0])
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    warped = cv2.warpPerspective(image, w, size, flags=flags)
    inside = cv2.warpPerspective(
        np.ones_like(image, np.uint8), w, size, flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    )
    if int(inside.sum()) < 0.25 * inside.size:
        return -1.0
    return float(cv2.computeECC(template, warped, inside))


# --- public API ---------------------------------------------------------------------------------


def estimate_alignment(
    frames: Sequence[np.ndarray | Callable[[], np.ndarray]],
    *,
    reference: int | None = None,
    model: str = "similarity",
    max_side_px: int = 768,
    chain: bool = True,
    method: str = "auto",
    min_correlation: float = 0.5,
    fallback: Sequence[Alignment] | None = None,
    workers: int = 1,
    names: Sequence[str] | None = None,
    breathing_px: float | None = BREATHING_TOLERANCE_PX,
) -> list[Alignment]:
    """Homographies that map every frame of a focal stack onto the reference frame (Sec. 9).

    Parameters
    ----------
    frames : sequence of ndarray or of zero-argument callables returning one
        Frames (rows, cols) or (rows, cols, channels), linear light, all the same
        size. Callables are called once each, so a caller can load lazily; only a
        reduced grey copy of each frame is kept.
    reference : int, optional
        Index of the reference frame; default the middle one, ``len(frames) // 2``.
    model : {"auto", "similarity", "breathing", "keystone", "affine", "homography"}
        Motion model. Focus breathing is a scaling about the optical centre
        (Fig. 1), a rail's or a steady hand's motion a shift and a turn: a
        similarity (4 degrees of freedom). A stack whose similarities all lie within
        ``breathing_px`` of the matching copy from one breathing about the
        image centre (:func:`breathing_about_centre`) gets that breathing (``model``
        "breathing"): its frames did not move, and the scaling alone leaves out the
        shifts and turns the blur differences lend each pair (rendered breathing
        stacks: corners 0.07 px from the truth against 0.17-0.21 px). "breathing"
        fits it whatever the frames' distance from it (a camera known not to move).
        "keystone" adds the two perspective
        terms of a wide-angle lens turned between frames (see ``_project``),
        "affine" adds shear and unequal scaling, "homography" all of these.
        Where the stack has no keystone their extra freedom fits the frames' blur
        differences (ECC's peak moves with them): on rendered breathing stacks a
        similarity's corners land 0.17-0.21 px from the true alignment, a
        keystone's 0.27-0.35 px, a homography's 0.29-0.35 px; on pcb7, pcb10 and
        amber a similarity's corners move by 0.9-5.6 px when the frames are
        cropped, a homography's by 2.2-12 px. On pcb7's copies seen through a
        16 mm lens turned by up to 0.25-1 degree, the keystone lands 0.67-0.77 px
        from the truth, the homography 1.12-1.25 px, the similarity 0.93-3.64 px
        (``tests/benchmarks/align_models.py``). "auto" fits the similarity and,
        where a neighbour pair shows a turn's keystone (``_turn_found``), the
        keystone for the whole stack; it costs one more half-resolution ECC per
        pair (0.04 s on the four real stacks' 768 px copies). It found every
        turned stack of the benchmark and left 43 variants of the real stacks
        alone, but reads a depth gradient across the frame as a turn (a 256 px
        stack of three planes: a pair's keystone took away 27% of the
        decorrelation, moved a corner by 1.8 px and fitted both halves alike),
        so it is not the default. ``Alignment.model`` says which model was fitted.
    max_side_px : int
        Longest side of the matching copy (the full-resolution result is exact
        conjugation of the reduced estimate, not a rounding of it).
    chain : bool
        Match each frame with its neighbour towards the reference and compose
        (defocus differs much less between neighbours than across the stack);
        False matches every frame with the reference directly.
    method : {"auto", "ecc", "features"}
        "ecc": coarse-to-fine ECC (``cv2.findTransformECC``) from the identity.
        "features": SIFT + RANSAC, refined by ECC at the finest level. "auto":
        ECC, and if it fails or correlates below 0.9 (or ``min_correlation``, if
        higher), features too; the better by ECC correlation on the overlap wins.
    min_correlation : float
        Minimum ECC correlation (on the matching copies) of an accepted estimate.
    fallback : sequence of Alignment, optional
        Per-frame transforms to use where estimation fails (e.g. from
        :func:`analytic_alignment`); default the anchor's (neighbour's) transform.
    workers : int
        Threads matching frame pairs (OpenCV releases the GIL). The pairs a chain
        will need are matched ahead, in parallel; the result does not depend on it.
    names : sequence of str, optional
        What to call each frame in messages (e.g. its file name); default ``frame i``.
    breathing_px : float or None
        The similarity's snap to the stack's breathing (see ``model``): the largest
        distance (px of the matching copy) of a frame from it; None never snaps a
        similarity (``model="breathing"`` is snapped whatever this is).

    Returns
    -------
    list of Alignment
        One per frame; failed frames carry ``ok=False``, the reason in
        ``message`` (also logged as a warning) and a finite fallback homography.

    Notes
    -----
    With chaining, a frame that fails does not become an anchor: the next frame
    outwards is matched with the last frame that succeeded.
    """
    n = len(frames)
    if n == 0:
        raise InputError("frames is empty; pass at least one frame")
    if model not in (*_MODELS, AUTO_MODEL):
        raise InputError(f"model must be one of {sorted([*_MODELS, AUTO_MODEL])}, got {model!r}")
    if method not in _METHODS:
        raise InputError(f"method must be one of {list(_METHODS)}, got {method!r}")
    if not isinstance(max_side_px, int | np.integer) or max_side_px < 2 * _COARSEST_SIDE_PX:
        raise InputError(
            f"max_side_px must be an int >= {2 * _COARSEST_SIDE_PX}, got {max_side_px!r}"
        )
    ref = n // 2 if reference is None else reference
    if not isinstance(ref, int | np.integer) or not 0 <= ref < n:
        raise InputError(f"reference must be a frame index in 0..{n - 1}, got {reference!r}")
    if fallback is not None and len(fallback) != n:
        raise InputError(f"fallback must have one Alignment per frame ({n}), got {len(fallback)}")
    if names is not None and len(names) != n:
        raise InputError(f"names must have one name per frame ({n}), got {len(names)}")
    if breathing_px is not None and not (
        isinstance(breathing_px, int | float | np.floating | np.integer)
        and math.isfinite(breathing_px)
        and breathing_px >= 0
    ):
        raise InputError(
            f"breathing_px must be a finite number of px >= 0, or None, got {breathing_px!r}"
        )
    label = [f"frame {i}" for i in range(n)] if names is None else [str(v) for v in names]

    full_shape: tuple[int, int] | None = None
    pyramids = []
    for i, frame in enumerate(frames):
        a = _load(frame, i)
        if full_shape is None:
            full_shape = a.shape[:2]
        elif a.shape[:2] != full_shape:
            raise InputError(
                f"frames[{i}] has size {a.shape[:2]} but frames[0] has {full_shape}; "
                "all frames of a stack must have the same size (crop or resize them first)"
            )
        img = _matching_image(a, max_side_px)
        del a
        if not np.all(np.isfinite(img)):
            raise InputError(f"frames[{i}] contains NaN or infinite values; fix or drop the frame")
        pyramids.append(_pyramid(img))
    assert full_shape is not None
    reduced = pyramids[0][-1].shape

    centre = ((full_shape[1] - 1) / 2, (full_shape[0] - 1) / 2)  # where scales are read
    features: dict[int, tuple] = {}

    def feats(k: int) -> tuple:
        if k not in features:
            features[k] = _features(pyramids[k][-1])
        return features[k]

    def match(i: int, j: int, fit: str) -> tuple[np.ndarray, float, str]:
        """Warp frame i -> frame j (reduced coordinates), its correlation and the method."""
        ti, tj = pyramids[i], pyramids[j]
        if _is_textureless(ti[-1]):
            raise _EstimationError(f"{label[i]} has no texture to match")
        if _is_textureless(tj[-1]):
            raise _EstimationError(f"{label[j]} has no texture to match")
        candidates: list[tuple[float, np.ndarray, str]] = []
        reasons = []
        if method in ("auto", "ecc"):
            try:
                w, cc = _ecc(ti, tj, np.eye(3), fit)
                candidates.append((cc, w, "ecc"))
            except _EstimationError as err:
                reasons.append(str(err))
        confident = [
            c
            for c in candidates
            if c[0] >= max(min_correlation, _CONFIDENT_CORRELATION)
            and not _implausible(c[1], reduced)
        ]
        if method == "features" or (method == "auto" and not confident):
            try:
                w = _project(_feature_warp(feats(i), feats(j), fit), fit, reduced)
                candidates.append((_correlation(ti[-1], tj[-1], w), w, "features"))
                w2, cc2 = _ecc(ti, tj, w, fit, start_level=len(ti) - 1)
                candidates.append((cc2, w2, "features+ecc"))
            except _EstimationError as err:
                reasons.append(str(err))
        for cc, w, how in sorted(candidates, key=lambda c: -c[0]):
            why = _implausible(w, reduced)
            if why:
                reasons.append(f"{how}: {why}")
            elif cc < min_correlation:
                reasons.append(f"{how}: correlation {cc:.3f} < min_correlation {min_correlation}")
            else:
                return w, cc, how
        raise _EstimationError("; ".join(reasons) or "no estimate")

    sides = (range(ref - 1, -1, -1), range(ref + 1, n))
    # The pair each frame is matched in if every match succeeds, started ahead of the chain.
    expected = [
        (i, side[k - 1] if chain and k else ref) for side in sides for k, i in enumerate(side)
    ]

    def solve(fit: str, pool: ThreadPoolExecutor) -> tuple[list[Alignment], dict]:
        """Every frame's alignment under the model ``fit``, and the pairs' reduced warps."""
        ahead = {pair: pool.submit(match, *pair, fit) for pair in expected}
        out: list[Alignment | None] = [None] * n
        out[ref] = Alignment(np.eye(3), 1.0, "reference", True, "", 1.0, fit)
        pairs: dict[tuple[int, int], np.ndarray] = {}
        for side in sides:
            anchor = ref
            for i in side:
                try:
                    pending = ahead.get((i, anchor))
                    w, cc, how = (
                        pending.result() if pending is not None else match(i, anchor, fit)
                    )
                    h = compose(out[anchor].homography, rescale_homography(w, reduced, full_shape))
                    why = _implausible(h, full_shape)
                    if why:
                        raise _EstimationError(f"composed transform: {why}")
                except _EstimationError as err:
                    base = fallback[i] if fallback is not None else out[anchor]
                    hint = "the given fallback" if fallback is not None else f"{label[anchor]}'s"
                    logger.warning(
                        "alignment of %s to %s failed (%s); using %s transform",
                        label[i],
                        label[anchor],
                        err,
                        hint,
                    )
                    h = _as_homography(base.homography)
                    out[i] = Alignment(
                        h, 1.0 / scale_of(h, centre), "fallback", False, str(err), None, fit
                    )
                    continue
                out[i] = Alignment(h, 1.0 / scale_of(h, centre), how, True, "", cc, fit)
                pairs[(i, anchor)] = w
                if chain:
                    anchor = i
        return out, pairs  # type: ignore[return-value]

    with ThreadPoolExecutor(
        max(1, min(workers, len(expected))), thread_name_prefix="align"
    ) as pool:
        out, pairs = solve("similarity" if model in (AUTO_MODEL, "breathing") else model, pool)
        if model == AUTO_MODEL:
            turn = _turn_found(pyramids, pairs, pool, label)
            if turn:
                logger.info("alignment: %s; fitting the keystone model", turn)
                out, _ = solve("keystone", pool)
    if model == "breathing" or (out[ref].model == "similarity" and breathing_px is not None):
        tolerance = math.inf if model == "breathing" else breathing_px
        out = _as_breathing(out, full_shape, max(reduced) / max(full_shape), tolerance)
    return out


def _as_breathing(
    out: list[Alignment], shape: tuple[int, int], to_matching: float, tolerance_px: float
) -> list[Alignment]:
    """``out`` as the stack's breathing about the image centre
    (:func:`breathing_about_centre`) where every frame lies within ``tolerance_px`` of it
    at the matching copy's scale (``to_matching`` px per full-resolution px), and every
    frame was estimated unless ``tolerance_px`` is infinite (then frames that failed keep
    their fallback)."""
    always = math.isinf(tolerance_px)
    if not always and not all(a.ok for a in out):
        return out
    models, distances = breathing_about_centre([a.homography for a in out], shape)
    farthest = float(distances.max()) * to_matching
    if farthest > tolerance_px:
        return out
    logger.info(
        "alignment: the frames lie within %.3f px (matching copy) of a breathing about the "
        "image centre; using it",
        farthest,
    )
    return [
        dataclasses.replace(a, homography=m, scale=1.0 / scale_of(m), model="breathing")
        if a.ok
        else a
        for a, m in zip(out, models)
    ]


def _centring(shape: tuple[int, int]) -> np.ndarray:
    """Maps coordinates centred on a ``shape`` image to its pixel coordinates."""
    return np.array([[1.0, 0, (shape[1] - 1) / 2], [0, 1.0, (shape[0] - 1) / 2], [0, 0, 1.0]])


def _centred_perspective(k: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The perspective row of ``k`` in coordinates centred on a ``shape`` image."""
    c = _centring(shape)
    centred = np.linalg.inv(c) @ k @ c
    return centred[2, :2] / centred[2, 2]


def _halves_spread(
    template: np.ndarray, image: np.ndarray, w: np.ndarray, whole: np.ndarray
) -> float:
    """How far the keystone's perspective row fitted on one half of ``template`` is from
    the one fitted on the other half (left/right, top/bottom, the larger), in units of the
    row of ``whole``, the keystone fitted on the whole frame: a turn's keystone is one for
    the whole frame, while blur differences fitted as perspective follow the content of
    each half. Each half is fitted from ``w``; a half that cannot be fitted (no texture)
    counts as disagreeing (infinite)."""
    rows, cols = template.shape
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-5)

    def fitted(mask: np.ndarray) -> np.ndarray:
        warp32 = w.astype(np.float32)
        try:
            _, warp32 = cv2.findTransformECC(
                template, image, warp32, cv2.MOTION_HOMOGRAPHY, criteria, mask, _ECC_GAUSS_SIZE
            )
        except cv2.error:
            return np.full(2, np.nan)
        return _centred_perspective(_project(warp32.astype(np.float64), "keystone", (rows, cols)),
                                    (rows, cols))  # fmt: skip

    halves = []
    parts = (np.s_[:, : cols // 2], np.s_[:, cols // 2 :], np.s_[: rows // 2], np.s_[rows // 2 :])
    for part in parts:
        mask = np.zeros((rows, cols), np.uint8)
        mask[part] = 1
        halves.append(fitted(mask))
    row = float(np.linalg.norm(_centred_perspective(whole, (rows, cols))))
    apart = [float(np.linalg.norm(a - b)) for a, b in (halves[:2], halves[2:])]
    if row <= 0 or not all(math.isfinite(a) for a in apart):  # max() would skip a NaN
        return math.inf
    return max(apart) / row


def _turn_evidence(
    template: list[np.ndarray], image: list[np.ndarray], w: np.ndarray
) -> tuple[float, float, float]:
    """What refining a pair's similarity ``w`` (finest-level coordinates) as a keystone at
    the half-resolution level shows: the share of the decorrelation left by ``w`` it takes
    away (both correlations by ``_correlation``), how far it moves a corner (px of the
    finest level) and, where these two pass ``_TURN_SHARE`` and ``_TURN_CORNER_PX``, the
    halves' spread (:func:`_halves_spread`; infinite where not measured or the refinement
    fails)."""
    level = max(len(template) - 2, 0)
    rows, cols = template[level].shape
    w = rescale_homography(w, template[-1].shape, (rows, cols))
    before = _correlation(template[level], image[level], w)
    try:
        k, _ = _ecc(template[: level + 1], image[: level + 1], w, "keystone", start_level=level)
    except _EstimationError:
        return 0.0, 0.0, math.inf
    if _implausible(k, (rows, cols)) or before >= 1.0:
        return 0.0, 0.0, math.inf
    share = (_correlation(template[level], image[level], k) - before) / (1.0 - before)
    corners = np.array([[0, cols - 1, 0, cols - 1], [0, 0, rows - 1, rows - 1], [1, 1, 1.0, 1]])
    a, b = k @ corners, w @ corners
    moved = float(np.hypot(*(a[:2] / a[2] - b[:2] / b[2])).max()) * template[-1].shape[0] / rows
    if share < _TURN_SHARE or moved < _TURN_CORNER_PX:
        return share, moved, math.inf
    return share, moved, _halves_spread(template[level], image[level], w, k)


def _turn_found(
    pyramids: list[list[np.ndarray]],
    pairs: dict[tuple[int, int], np.ndarray],
    pool,
    label: Sequence[str],
) -> str:
    """Which neighbour pair shows a turn's keystone ('' where none does), for "auto";
    ``label`` names the frames.

    A turn is seen where refining the pair's similarity as a keystone
    (:func:`_turn_evidence`) takes away ``_TURN_SHARE`` or more of its decorrelation, moves
    a corner by ``_TURN_CORNER_PX`` or more, and the halves of the frame agree on it (their
    rows at most ``_TURN_SPREAD`` times the whole row apart). Blur differences pass the
    first two on some stacks that were not turned (pcb10 cropped by 20%, amber cropped or
    halved), but fit each half differently (6.1-9.2 apart); turned stacks' halves agree
    within 0.08-1.27 (``tests/benchmarks/align_models.py``, its last table). A first
    version asked instead that the perspective row point along the pair's shift, as a pure
    turn's does; a hand's shift mixed in breaks that (pcb7 turned by up to 0.5 degree and
    shifted by up to 1%: 2 of 20 seeds missed).
    """

    def evidence(pair: tuple[int, int]) -> tuple[float, float, float]:
        return _turn_evidence(pyramids[pair[0]], pyramids[pair[1]], pairs[pair])

    for (i, j), (share, moved, spread) in zip(pairs, pool.map(evidence, pairs)):
        if spread <= _TURN_SPREAD:
            return (
                f"{label[i]} and {label[j]} differ by a turn's keystone (it takes away "
                f"{share:.0%} of the decorrelation a similarity leaves and moves a corner by "
                f"{moved:.1f} px of the matching copy)"
            )
    return ""


def analytic_alignment(
    image_distances_mm: Sequence[float],
    shape: tuple[int, ...],
    *,
    reference: int | None = None,
    centre: tuple[float, float] | None = None,
) -> list[Alignment]:
    """Pure scalings about the optical centre predicted from the focus positions (Fig. 1).

    Parameters
    ----------
    image_distances_mm : sequence of float
        Focus position ``p_i`` (lens-to-detector distance, mm) of every frame.
    shape : tuple
        Frame shape; only (rows, cols) is used.
    reference : int, optional
        Index of the reference frame; default ``len // 2``.
    centre : (x, y), optional
        Optical centre in pixels; default the image centre ``((cols-1)/2, (rows-1)/2)``.

    Returns
    -------
    list of Alignment
        ``H_i`` scales by ``p_ref / p_i`` about ``centre``; ``scale = p_i / p_ref``.

    Notes
    -----
    In Fig. 1 the chief ray through the lens centre is undeviated, so a scene
    point at lateral offset ``X`` and distance ``u`` images (in focus or as the
    centre ``m'`` of its blur circle) at radius ``r = p X / u`` on a detector at
    distance ``p``: the magnification is ``p / u`` (footnote 1). For the same
    scene ``r_i / r_ref = p_i / p_ref``, so frame i maps to the reference by a
    scaling of ``p_ref / p_i`` about the optical centre. With a moving lens
    (Sec. 8) ``u`` changes by the same small step, neglected here.
    """
    p = np.asarray(image_distances_mm, dtype=np.float64).ravel()
    if p.size == 0 or not np.all(np.isfinite(p)) or np.any(p <= 0):
        raise InputError(
            "image_distances_mm must be finite and > 0 (mm from the lens to the detector), "
            f"got {p.tolist()}"
        )
    if len(shape) < 2 or shape[0] < 1 or shape[1] < 1:
        raise InputError(f"shape must start with (rows, cols) >= 1, got {shape!r}")
    n = p.size
    ref = n // 2 if reference is None else reference
    if not isinstance(ref, int | np.integer) or not 0 <= ref < n:
        raise InputError(f"reference must be a frame index in 0..{n - 1}, got {reference!r}")
    cx, cy = ((shape[1] - 1) / 2, (shape[0] - 1) / 2) if centre is None else centre
    out = []
    for i, p_i in enumerate(p):
        s = p[ref] / p_i
        h = np.array([[s, 0.0, cx * (1 - s)], [0.0, s, cy * (1 - s)], [0.0, 0.0, 1.0]])
        out.append(Alignment(h, float(p_i / p[ref]), "reference" if i == ref else "analytic"))
    return out


def warp(
    frame: np.ndarray,
    homography: np.ndarray,
    shape: tuple[int, ...],
    *,
    return_coverage: bool = False,
    interpolation: str = "linear",
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Resample ``frame`` onto the reference grid: ``out(H x) = frame(x)``.

    Parameters
    ----------
    frame : ndarray, (rows, cols) or (rows, cols, channels)
        float32 stays float32; other dtypes return float64 (resampled in float32,
        see Notes).
    homography : ndarray, (3, 3)
        Frame pixel coordinates -> reference pixel coordinates (``Alignment.homography``).
    shape : tuple
        Output (rows, cols[, ...]); only the first two entries are used.
    return_coverage : bool
        Also return a float32 (rows, cols) map of how much of each output pixel
        came from inside the frame (1 inside, 0 outside, fractional on the edge),
        for renormalising a weighted average.
    interpolation : {"linear", "cubic", "lanczos"}
        "linear" (bilinear) for averages (see Notes); "lanczos" (Lanczos-4, 8x8 taps)
        where a single frame's fine detail is used as it is (the multi-frame method):
        bilinear resampling at a half-pixel offset halves the response at 0.35
        cycles/px, Lanczos keeps it within a few percent (and may overshoot at edges).
        "cubic" (4x4 taps, 6x faster than Lanczos on a 2048x1536 frame) keeps it within
        3% up to 0.25 cycles/px and at 0.72 at 0.35 (the end frames' detail bands,
        :func:`pipeline.jobs.ends.keep_end_detail`).

    Returns
    -------
    ndarray or (ndarray, ndarray)
        The warped frame, shape ``shape[:2] + frame.shape[2:]``, and optionally coverage.

    Notes
    -----
    ``cv2.warpPerspective`` evaluates ``out(y) = frame(H^-1 y)``; ``H^-1`` is
    computed here in float64 and passed with ``WARP_INVERSE_MAP``. Bilinear
    interpolation (INTER_LINEAR) is a convex combination of neighbours, so linear
    light stays non-negative and no ringing enters the average (cubic kernels
    overshoot at edges). Borders replicate the edge pixels so no black enters an
    average; ``coverage`` says which pixels are extrapolated. OpenCV 5 interpolates
    float32 images of 1, 3 or 4 channels at exact positions but quantises positions
    to 1/32 px for float64, 2 channels or over 4, so resampling runs on float32 groups
    of 1, 3 or 4 channels (float32 rounding, ~6e-8 relative, is far smaller).

    Bilinear resampling goes through ``cv2.remap`` with the positions computed here
    (:func:`_remap_linear`): OpenCV 5.1's bilinear ``warpPerspective`` and
    ``warpAffine`` give results that depend on how its thread pool splits the rows (a
    float32 ulp in a few dozen pixels of a 3 Mpx frame), and the split depends on
    whether another thread holds the pool at that moment, so two runs of one stack
    differed by up to 2 codes of 65535 in thousands of pixels. Its cubic and Lanczos
    warps, and ``remap``, do not.
    """
    a = _checked_frame(frame, "frame")
    if len(shape) < 2 or int(shape[0]) < 1 or int(shape[1]) < 1:
        raise InputError(f"shape must start with (rows, cols) >= 1, got {shape!r}")
    inverse = np.linalg.inv(_as_homography(homography))
    rows, cols = int(shape[0]), int(shape[1])
    src = a.astype(np.float32, copy=False)
    if interpolation not in _INTERPOLATIONS:
        raise InputError(
            f"interpolation must be one of {sorted(_INTERPOLATIONS)}, got {interpolation!r}"
        )
    if (rows, cols) == src.shape[:2] and np.array_equal(inverse, np.eye(3)):
        # the identity (a reference frame): exact, where OpenCV 5.1 resamples a float32
        # pixel an ulp off
        out = src.copy() if a.dtype == np.float32 else src.astype(np.float64)
        return (out, np.ones((rows, cols), np.float32)) if return_coverage else out
    flags = _INTERPOLATIONS[interpolation] | cv2.WARP_INVERSE_MAP
    size = (cols, rows)
    channels = 1 if src.ndim == 2 else src.shape[2]
    parts = []
    for c0 in range(0, channels, 4):  # exact sub-pixel path: float32, <= 4 channels per call
        part = src if src.ndim == 2 else np.ascontiguousarray(src[..., c0 : c0 + 4])
        w = _warp_exact(part, inverse, size, flags)
        parts.append(w.reshape(rows, cols, -1) if src.ndim == 3 else w)
    out = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=2)
    if a.dtype != np.float32:
        out = out.astype(np.float64)
    if not return_coverage:
        return out
    ones = np.ones(a.shape[:2], np.float32)
    coverage = _resample(ones, inverse, size, flags, cv2.BORDER_CONSTANT)
    return out, coverage


# rows of positions made at once for the bilinear remap (two float32 maps of 1 MB at 2048 px)
REMAP_STRIP_ROWS = 128


def _remap_linear(image: np.ndarray, inverse: np.ndarray, size: tuple[int, int], border: int):
    """Bilinear ``out(x, y) = image(H^-1 (x, y))`` by ``cv2.remap``, by strips of
    ``REMAP_STRIP_ROWS`` rows: the same value for a pixel whatever the strips or OpenCV's
    threads (see :func:`warp`). Positions are float32 sums of float64 row and column
    terms (about 5e-4 px at worst at 4096 px, far under the interpolation's own 1/32 px
    steps where OpenCV quantises), divided by the homogeneous coordinate where ``H^-1`` is
    not affine."""
    cols, rows = size
    x = np.arange(cols, dtype=np.float64)
    affine = inverse[2, 0] == 0 and inverse[2, 1] == 0
    rows_of = 2 if affine else 3  # an affine H^-1's homogeneous coordinate is its constant
    terms = [(inverse[k, 0] * x).astype(np.float32)[None, :] for k in range(rows_of)]
    out = np.empty((rows, cols, *image.shape[2:]), image.dtype)
    flat = out.reshape(rows, cols, -1) if out.ndim == 3 else out
    target = flat[..., 0] if flat.ndim == 3 and flat.shape[2] == 1 else flat  # (r, c, 1) too
    for r0 in range(0, rows, REMAP_STRIP_ROWS):
        y = np.arange(r0, min(rows, r0 + REMAP_STRIP_ROWS), dtype=np.float64)
        u, v, *w = (
            terms[k] + (inverse[k, 1] * y + inverse[k, 2]).astype(np.float32)[:, None]
            for k in range(rows_of)
        )
        if w:
            u, v = u / w[0], v / w[0]
        elif inverse[2, 2] != 1.0:
            u, v = u / np.float32(inverse[2, 2]), v / np.float32(inverse[2, 2])
        # straight into the output's rows (9 against 15 ms on a 3 Mpx RGB frame: no copy,
        # each strip written while it is in cache)
        cv2.remap(image, u, v, cv2.INTER_LINEAR, dst=target[r0 : r0 + len(y)], borderMode=border)
    return out


def _resample(image: np.ndarray, inverse: np.ndarray, size, flags: int, border: int):
    """``cv2.warpPerspective(image, inverse, size, flags | WARP_INVERSE_MAP, border)``,
    bilinear through :func:`_remap_linear` (thread-independent)."""
    if flags & cv2.INTER_MAX == cv2.INTER_LINEAR:
        return _remap_linear(image, inverse, size, border)
    return cv2.warpPerspective(image, inverse, size, flags=flags, borderMode=border)


def _warp_exact(part: np.ndarray, inverse: np.ndarray, size: tuple[int, int], flags: int):
    """The warp (:func:`_resample`) of a float32 group of at most 4 channels, edge-replicated.

    OpenCV 5.0 resamples 2-channel float32 images at positions quantised to 1/32 px (up
    to 1.6% of the pixel range off on a noisy image), 1, 3 and 4 channels exactly: two
    channels are warped one at a time.
    """
    if part.ndim == 3 and part.shape[2] == 2:
        return np.dstack(
            [
                _warp_exact(np.ascontiguousarray(part[..., k]), inverse, size, flags)
                for k in range(2)
            ]
        )
    return _resample(part, inverse, size, flags, cv2.BORDER_REPLICATE)
