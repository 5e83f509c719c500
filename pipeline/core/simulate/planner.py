"""Which effects a scene needs at a tolerance (``simulate only the effects a scene
calls for``): depth layers, occlusion, magnification steps, rolling-shutter rows and
noise, each with its estimated error (:func:`plan`).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import itertools
import math

import numpy as np
from scipy import fft as sfft

from pipeline.core import optics, psf, spectra, validate
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile
from pipeline.core.scene import Camera, Exposure, Scene, mean_position
from pipeline.core.simulate import composite
from pipeline.core.simulate import edge as edge_model
from pipeline.errors import InputError

REFERENCE_GRID = 256
EDGE_BLUR_PX = 1.0
MAX_LAYERS = 4000
MAX_MAGNIFICATION_STEPS = 64
MAX_EDGE_TIME_CELLS = 64  # per magnification sub-step
EDGE_WORK_BUDGET = 2e8  # aperture cells x time cells x layers x px of sub-aperture compositing
_MAG_NODES = 48
_CHECK_DEPTHS = 5
_GAIN_PIXELS = 1024  # pixels of a band at which _Gain evaluates the gain error
_GAIN_BLOCK = 1 << 21  # window values (pixels x kernel area) per _Gain evaluation
_GAIN_DEPTHS = 257  # true kernels per _Gain evaluation (beyond: nodes uniform in D)


# ----------------------------------------------------------------------------- the metric
def _grid(size: int) -> int:
    return max(REFERENCE_GRID, 1 << (2 * size - 1).bit_length())


@dataclasses.dataclass
class _Spectra:
    """Kernel spectra on one ``n x n`` grid (real FFT half-plane) and the weights |F|^2."""

    n: int

    def __post_init__(self) -> None:
        full = spectra.natural_image_spectrum((self.n, self.n))
        half = full[:, : self.n // 2 + 1].copy()
        half[:, 1 : (self.n + 1) // 2] *= 2  # columns that stand for their conjugate too
        self.weights = half
        self.fy = sfft.fftfreq(self.n)[:, None]
        self.fx = sfft.rfftfreq(self.n)[None, :]

    def of(self, kernel: np.ndarray) -> np.ndarray:
        return spectra.centred_fft(kernel, (self.n, self.n), real=True)

    def error(self, diff: np.ndarray) -> float:
        return float(np.sqrt(np.sum((diff.real**2 + diff.imag**2) * self.weights)))

    def shift(self, dx: float, dy: float) -> np.ndarray:
        # separable: two 1-D exponentials instead of one per frequency
        return np.exp(-2j * np.pi * self.fy * dy) * np.exp(-2j * np.pi * self.fx * dx)

    def shifted_sum(self, kernels: np.ndarray, shifts: np.ndarray) -> np.ndarray:
        """``sum_q of(kernels[q]) * shift(*shifts[q])`` without an FFT per kernel.

        Parameters
        ----------
        kernels : ndarray, shape (N, s, s)
            Odd-sized, centred kernels.
        shifts : ndarray, shape (N, 2)
            Each kernel's displacement ``(dx, dy)`` in px.

        Returns
        -------
        ndarray
            The half-plane spectrum on the ``n x n`` grid.

        Notes
        -----
        The DFT of a centred kernel displaced by ``(dx, dy)`` is separable,
        ``sum_ij k_ij exp(-2 pi i (fy (i - h + dy) + fx (j - h + dx)))``, ``h = s // 2``:
        one ``(s x s) @ (s x n/2+1)`` product per kernel and one
        ``(n x N s) @ (N s x n/2+1)`` product for the sum (cheaper than ``N`` FFTs of the
        grid while ``N s`` is below about ``n log n``).
        """
        count, size = kernels.shape[:2]
        offsets = (np.arange(size) - size // 2)[:, None]

        def phases(f, d):  # (N, s, len(f)): exp(-2 pi i (offset + d_q) f)
            return np.exp(-2j * np.pi * offsets * f) * np.exp(-2j * np.pi * d[:, None, None] * f)

        ex, ey = phases(self.fx, shifts[:, 0]), phases(self.fy.T, shifts[:, 1])
        rows = np.matmul(kernels, ex)  # (N, s, n/2+1): sum over each kernel's columns
        return ey.reshape(count * size, -1).T @ rows.reshape(count * size, -1)


def kernel_error(k1: np.ndarray, k2: np.ndarray) -> float:
    """RMS image change (per unit RMS contrast of a 1/f natural image) from ``k1`` -> ``k2``.

    ``sqrt(sum_w |K1 - K2|^2 |F(w)|^2)`` on a 256 px grid (larger for kernels over 128 px);
    the tolerance of :func:`plan` means this everywhere. Kernels: odd, centred.
    """
    k1, k2 = np.asarray(k1, float), np.asarray(k2, float)
    for name, k in (("k1", k1), ("k2", k2)):
        if k.ndim != 2 or k.shape[0] != k.shape[1] or k.shape[0] % 2 == 0:
            raise InputError(f"{name} must be a square kernel of odd size, got shape {k.shape}")
    spectra = _Spectra(_grid(max(k1.shape[0], k2.shape[0])))
    return spectra.error(spectra.of(k1) - spectra.of(k2))


# ----------------------------------------------------------------------------- plan
@dataclasses.dataclass(frozen=True)
class Effect:
    """One effect the plan considered: applied or skipped, why, and the error of skipping it."""

    name: str
    applied: bool
    reason: str
    estimated_error: float


@dataclasses.dataclass(frozen=True)
class Layer:
    """Depth layer: inverse depths (1/mm) it covers, ``(lo, hi]``, and its representative."""

    inv_lo: float
    inv_hi: float
    inv_rep: float
    group: int = 0  # layers of one group (overlapping surface depth ranges) interpolate

    @property
    def depth_mm(self) -> float:
        return _depth(self.inv_rep)


@dataclasses.dataclass(frozen=True, eq=False)
class Step:
    """A sub-step of the exposure: its motion, its image scale ``p / p_ref`` and time weight."""

    profile: Profile
    scale: float
    weight: float


@dataclasses.dataclass(frozen=True, eq=False)
class Band:
    """Rows ``[row_start, row_stop)`` rendered with one motion window, layers and sub-steps."""

    row_start: int
    row_stop: int
    profile: Profile
    layers: tuple[Layer, ...]
    steps: tuple[Step, ...]


@dataclasses.dataclass(frozen=True, eq=False)
class Plan:
    """What :func:`render` will simulate for one capture, and why (see :meth:`explain`)."""

    tolerance: float
    shape: tuple[int, int]
    lens: Lens
    model: str
    bands: tuple[Band, ...]
    occlusion: bool
    edge_inv_depth: float
    noise: Exposure | None
    effects: tuple[Effect, ...]
    edge_time_cells: int = 0  # > 0: sub-aperture compositing at occluding edges

    @property
    def layer_count(self) -> int:
        return max(len(b.layers) for b in self.bands)

    @property
    def convolutions(self) -> int:
        """FFT convolutions the render costs (one per layer per sub-step per band)."""
        return sum(len(b.layers) * len(b.steps) for b in self.bands)

    @property
    def estimated_error(self) -> float:
        """Sum of the estimated errors of everything approximated or skipped."""
        return float(sum(e.estimated_error for e in self.effects))

    def explain(self) -> str:
        """Human-readable account of each effect: applied or skipped, reason, estimated error."""
        rows, cols = self.shape
        lines = [
            f"simulation plan: {rows}x{cols} px, lens {self.lens.name!r}, {self.model} PSF, "
            f"tolerance {self.tolerance:g} (RMS image error per unit RMS contrast, "
            "1/f natural image)",
        ]
        for e in self.effects:
            state = "apply" if e.applied else "skip "
            lines.append(f"  [{state}] {e.name}: {e.reason} (est. error {e.estimated_error:.2g})")
        lines.append(
            f"  cost: {self.convolutions} FFT convolution(s) ({len(self.bands)} band(s), "
            f"up to {self.layer_count} layer(s))"
        )
        return "\n".join(lines)


def _depth(inv: float) -> float:
    return math.inf if inv <= 0 else 1.0 / inv


def _mean_power(shape: tuple[int, int]) -> float:
    """Mean of ``1 / |w|^2`` over the non-zero frequencies of a ``shape`` grid (w in cycles/px)."""
    fy = sfft.fftfreq(shape[0])[:, None]
    fx = sfft.fftfreq(shape[1])[None, :]
    total = 0.0
    for i in range(0, shape[0], 256):  # blocks of rows: a full-sensor grid stays small
        w2 = fy[i : i + 256] ** 2 + fx**2
        if i == 0:
            w2[0, 0] = math.inf
        total += float(np.sum(1.0 / w2))
    return total / (shape[0] * shape[1] - 1)


def _finite_scene_factor(shape: tuple[int, int], n: int) -> float:
    """Image error of a ``shape`` scene per unit :func:`kernel_error` on the ``n x n`` grid.

    Parameters
    ----------
    shape : tuple of int
        The scene's rows and columns.
    n : int
        The grid :func:`kernel_error` is measured on (``REFERENCE_GRID`` or larger).

    Returns
    -------
    float
        ``sqrt(mean_n(1/|w|^2) / mean_shape(1/|w|^2))``: 1.31 for 16x32 px, 1.18 for
        48x64, 1 for 256x256, 0.84 for 2592x1944.

    Notes
    -----
    ``kernel_error`` weighs each frequency of the ``n x n`` grid by a 1/f image of unit
    RMS contrast there: ``|F(w)|^2 = S(w) / sum_n S``, ``S = 1/|w|^2``. The error of a
    kernel change ``dK`` on a ``r x c`` scene with the same 1/f statistics and unit RMS
    contrast over its own pixels is ``sum_rc |dK|^2 S / sum_rc S``; both sums sample one
    smooth ``|dK|^2 S`` density at ``n^2`` or ``r c`` frequencies, so the squared ratio is
    ``(sum_n S / n^2) / (sum_rc S / (r c))``. A small scene's contrast lacks the low
    frequencies below ``1 / size`` (its mean), so the same kernel change is a larger part
    of it: estimates measured on the 256 px grid were low by this factor on the reference
    suite's 16x32 and 48x64 px scenes. A scene larger than the grid has more contrast at
    low frequencies, which blur does not change: the factor is below 1.
    """
    return math.sqrt(_mean_power((n, n)) / _mean_power(shape))


def _present_inverse_depths(scene: Scene, lens: Lens) -> np.ndarray:
    values = []
    for s in scene.surfaces:
        d = s.depth_mm[s.alpha > 0]
        if d.size and d.min() <= lens.focal_length_mm:
            raise InputError(
                f"scene depth {d.min():.6g} mm is not beyond the focal length "
                f"{lens.focal_length_mm} mm (no real image); move the scene farther"
            )
        values.append(1.0 / d)  # inf -> 0
    present = np.unique(np.concatenate(values))
    if present.size == 0:
        raise InputError("the scene has no pixel with alpha > 0; nothing to render")
    return present


class _Lru(collections.OrderedDict):
    """A dict of arrays that drops its least recently used entries beyond ``budget`` bytes
    (the plan of a rolling-shutter capture asks for spectra of thousands of row windows)."""

    def __init__(self, budget: int) -> None:
        super().__init__()
        self.budget, self.nbytes = budget, 0

    def __contains__(self, key) -> bool:
        if super().__contains__(key):
            self.move_to_end(key)
            return True
        return False

    def __setitem__(self, key, value) -> None:
        if super().__contains__(key):
            self.nbytes -= self[key].nbytes
        super().__setitem__(key, value)
        self.nbytes += value.nbytes
        while self.nbytes > self.budget and len(self) > 1:
            _, old = self.popitem(last=False)
            self.nbytes -= old.nbytes

    def clear(self) -> None:
        super().clear()
        self.nbytes = 0


class _KernelCache:
    """IPSF kernels and spectra per (inverse depth, motion window)."""

    def __init__(self, lens: Lens, model: str, spectra: _Spectra, budget: int = 48 << 20) -> None:
        self.lens, self.model, self.spectra = lens, model, spectra
        self._k: _Lru = _Lru(budget)
        self._s: _Lru = _Lru(budget)

    def clear(self) -> None:
        self._k.clear()
        self._s.clear()

    def kernel(self, inv: float, profile: Profile, scale: float = 1.0) -> np.ndarray:
        """The IPSF in grid pixels of a sub-step later scaled by ``scale`` (``p / p_ref``).

        The detector blur of Eq. 2 is ``b`` detector px; the step is rendered on the
        reference grid and then scaled by ``scale``, so its kernel is ``b / scale`` grid px:
        the pitch times ``scale``.
        """
        key = (inv, id(profile), scale)
        if key not in self._k:
            lens = self.lens
            if scale != 1.0:
                lens = dataclasses.replace(lens, pixel_pitch_um=lens.pixel_pitch_um * scale)
            kernel = psf.integrated_psf(lens, _depth(inv), profile, model=self.model)
            self._k[key] = kernel
            return kernel
        return self._k[key]

    def spectrum(self, inv: float, profile: Profile, scale: float = 1.0) -> np.ndarray:
        key = (inv, id(profile), scale)
        if key not in self._s:
            spectrum = self.spectra.of(self.kernel(inv, profile, scale))
            self._s[key] = spectrum
            return spectrum
        return self._s[key]


def _partition(present, lo, hi, dist, tol, *, integer: bool):
    """Greedy split of ``[lo, hi]`` into parts whose members are within ``tol`` of a representative.

    Samples are refined by bisection (where scene values are present) until neighbours are
    within ``tol / 3``; parts are grown greedily to ``2 tol / 3`` from a representative
    sample, so by the triangle inequality (``kernel_error`` is a norm) every present value
    is within about ``tol`` of its part's representative (exact if the kernel changes
    monotonically between neighbouring samples). An interval is also split when its ends
    agree but its middle does not: a kernel can turn back (a window sweeping through
    focus blurs depths on either side alike; a rolling-shutter row whose whole depth
    range was one layer rendered 0.22 off the reference). Returns ``[(end, rep), ...]``,
    the largest estimated error and the sorted samples (neighbours within about ``tol / 3``
    wherever scene values lie between them).
    """
    samples = {lo, hi}
    stack, gap = [(lo, hi)], 0.0
    while stack:
        a, b = stack.pop()
        if np.searchsorted(present, b, "left") <= np.searchsorted(present, a, "right"):
            continue  # no scene value strictly inside
        m = (a + b) // 2 if integer else a + 0.5 * (b - a)
        d = dist(a, b) if m in (a, b) else max(dist(a, b), dist(a, m))
        if d > tol / 3 and m not in (a, b):
            samples.add(m)
            stack += [(a, m), (m, b)]
        else:
            gap = max(gap, d if m not in (a, b) else 0.0)
    xs = sorted(samples)
    parts, worst, i = [], 0.0, 0
    while True:
        j = i
        while j + 1 < len(xs) and dist(xs[i], xs[j + 1]) <= 2 * tol / 3:
            j += 1
        e = j
        while e + 1 < len(xs) and dist(xs[j], xs[e + 1]) <= 2 * tol / 3:
            e += 1
        worst = max(worst, dist(xs[i], xs[j]), dist(xs[j], xs[e]))
        parts.append((xs[e], xs[j]))
        if len(parts) > MAX_LAYERS:
            raise InputError(
                f"tolerance {tol:g} needs more than {MAX_LAYERS} layers/bands; raise the tolerance"
            )
        k = int(np.searchsorted(present, xs[e], side="right"))
        if k >= present.size:
            break
        i = max(int(np.searchsorted(xs, present[k], side="right")) - 1, e + 1)
    return parts, worst + gap, np.array(xs)


def _near(scene: Scene, q0: int, q1: int) -> np.ndarray:
    """The inverse depths present in rows ``[q0, q1)`` (those that blur into a band's rows)."""
    return np.unique(
        np.concatenate([1.0 / s.depth_mm[q0:q1][s.alpha[q0:q1] > 0] for s in scene.surfaces])
    )


def _groups(scene: Scene, present: np.ndarray) -> list[np.ndarray]:
    """Present inverse depths split into groups of surfaces whose depth ranges overlap.

    Layers never span two groups: two planes whose kernels happen to agree (focus between
    them) stay in separate layers, so that the nearer one can occlude the farther.
    """
    spans = sorted(
        (float(inv.min()), float(inv.max()))
        for inv in (1.0 / s.depth_mm[s.alpha > 0] for s in scene.surfaces)
        if inv.size
    )
    merged: list[list[float]] = []
    for lo, hi in spans:
        if merged and lo <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    return [present[(present >= lo) & (present <= hi)] for lo, hi in merged]


def _layers(groups, near, profile, cache: _KernelCache, tol, *, hat: bool, gain=None):
    """Depth layers of each group (:func:`_partition` in inverse depth by ``kernel_error``).

    Returns the layers, the largest box-layer error, for hat-function layers (``hat``) the
    check depths ``[(d, a, b), ...]`` of :func:`_hat_split` over the inverse depths
    ``near`` (those whose blur reaches the band's rows; empty for box layers), and the
    gain error. ``gain``: ``layers -> (gain error, inverse depth)`` (:meth:`_Gain.error`);
    while the gain error exceeds ``tol`` that depth becomes a representative too.
    """

    def dist(a, b):
        return cache.spectra.error(cache.spectrum(a, profile) - cache.spectrum(b, profile))

    def blend(d, a, b):
        t = (d - a) / (b - a)
        k = cache.spectrum(d, profile) - (1 - t) * cache.spectrum(a, profile)
        return cache.spectra.error(k - t * cache.spectrum(b, profile))

    worst, split = 0.0, []
    for present in groups:
        lo, hi = float(present[0]), float(present[-1])
        parts, err, samples = _partition(present, lo, hi, dist, tol, integer=False)
        worst = max(worst, err)
        split.append((lo, hi, parts, samples, present[np.isin(present, near)]))
    extra: list[float] = []
    while True:
        layers, start, checks = [], -math.inf, []
        for g, (lo, hi, parts, samples, mine) in enumerate(split):
            if hat:
                forced = [d for d in extra if lo <= d <= hi]
                parts, group_checks = _hat_split(parts, samples, mine, blend, tol, forced)
                checks += group_checks
            for end, rep in parts:
                layers.append(Layer(start, end, rep, g))
                start = end
        if len(layers) > MAX_LAYERS:
            raise InputError(
                f"tolerance {tol:g} needs more than {MAX_LAYERS} layers; raise the tolerance"
            )
        g_err, depth = (0.0, None) if gain is None else gain(tuple(layers))
        if g_err <= tol or depth is None or depth in extra:  # (a depth of no group's range)
            return tuple(layers), worst, checks, g_err
        extra.append(depth)


def _hat_split(parts, samples, present, blend, tol, forced=()):
    """Add representatives until the hat-function blend is within ``tol`` between each two.

    A pixel at inverse depth ``d`` between representatives ``a < b`` is rendered with
    ``(1 - t) K(a) + t K(b)``, ``t = (d - a) / (b - a)``; its error ``blend(d, a, b)`` is
    0 at the ends but need not be largest in the middle: where a window sweeps through
    focus the kernel changes fastest near one end (a rolling capture with depth down the
    rows had 0.0045 next to an end, 0.0029 at the middle). It is checked at the scene
    depths nearest the middle and nearest each sample of :func:`_partition` inside
    ``(a, b)`` (neighbours within about ``tol / 3``: the samples follow the kernel's
    changes; a depth with no pixel is not checked); while the worst exceeds ``tol`` it
    becomes a representative (exact there) and both halves are checked again. Returns the
    parts ``[(end, rep), ...]`` (a split part's new boundaries halfway between its
    representatives) and the worst check depth of each interval with scene depths,
    ``[(d, a, b), ...]``. ``forced``: inverse depths (within the parts) that are
    representatives from the start.
    """
    reps = [rep for _, rep in parts]
    added = sorted(set(forced) - set(reps))
    checks = []
    stack = list(itertools.pairwise(sorted(reps + added)))
    while stack:
        a, b = stack.pop()
        inside = present[(present > a) & (present < b)]
        if not inside.size:
            continue
        targets = [0.5 * (a + b), *samples[(samples > a) & (samples < b)]]
        j = np.searchsorted(inside, targets).clip(1, inside.size - 1) if inside.size > 1 else 0
        nearer = np.abs(inside[j - 1] - targets) < np.abs(inside[j] - targets)
        points = {float(d) for d in np.where(nearer, inside[j - 1], inside[j])}
        errors = {d: blend(d, a, b) for d in points}
        d = max(errors, key=errors.get)
        if errors[d] > tol:
            added.append(d)
            stack += [(a, d), (d, b)]
        else:
            checks.append((d, a, b))
    if not added:
        return parts, checks
    all_reps = np.array(sorted(reps + added))
    split, start = [], -math.inf
    for end, _ in parts:
        mine = all_reps[(all_reps > start) & (all_reps <= end)]
        split += list(zip([*(0.5 * (mine[1:] + mine[:-1])), end], mine))
        start = end
    return split, checks


def _hat_error(groups, near, layers, checks, steps, cache: _KernelCache, shape) -> float:
    """Estimated error of the hat-function layers as rendered (``render._hat``).

    At the check depth of each interval between neighbouring representatives (``checks``,
    the worst of :func:`_hat_split`) and at the depths beyond a group's end
    representatives (which keep the end kernel; of the inverse depths ``near`` the band's
    rows), the image error of the interpolated kernel, summed over the sub-steps as they
    are rendered:
    ``|| sum_s w_s (K_s(D) - (1 - t) K_s(a) - t K_s(b)) exp(-i w . delta_s) ||`` with each
    step's grid kernel (pitch x scale) and its displacement ``delta_s = (scale_s - 1) r``
    at the image's RMS radius ``r``.
    """
    spectra = cache.spectra
    radius = np.array([shape[1], shape[0]]) / math.sqrt(12)
    shifts = [spectra.shift(*((st.scale - 1) * radius)) for st in steps]

    def err(d, terms):
        total = 0
        for st, sh in zip(steps, shifts):
            k = cache.spectrum(d, st.profile, st.scale)
            for w, r in terms:
                k = k - w * cache.spectrum(r, st.profile, st.scale)
            total = total + st.weight * (k if len(steps) == 1 else k * sh)
        return spectra.error(total)

    worst = 0.0
    for g, present in enumerate(groups):
        present = present[np.isin(present, near)]
        reps = [layer.inv_rep for layer in layers if layer.group == g]
        for end, beyond in (
            (reps[0], present[present < reps[0]]),
            (reps[-1], present[present > reps[-1]]),
        ):
            if beyond.size:
                far = beyond[0] if end == reps[0] else beyond[-1]
                worst = max(worst, err(float(far), [(1.0, end)]))
    for d, a, b in checks:
        t = (d - a) / (b - a)
        worst = max(worst, err(d, [(1 - t, a), (t, b)]))
    return worst


class _Gain:
    """The mean-radiance error of hat layers where the depth changes within a kernel.

    Parameters
    ----------
    scene : Scene
    present : ndarray
        The scene's sorted inverse depths (:func:`_present_inverse_depths`).
    half : int
        The largest kernel half-size of the capture.

    Notes
    -----
    Each scene point spreads its light with the kernel of its own depth, so pixel ``p``
    gathers ``sum_delta K_{D(p - delta)}(delta) L(p - delta)`` and the layers' error there
    is ``sum_delta E_{D(p - delta)}(delta) L(p - delta)``, ``E_D = K_a(D) - K(D)`` the
    rendered (hat-blended) kernel minus the true one. Where ``D`` is constant over the
    kernel, ``E_D`` sums to 0 and the error is the zero-mean part that
    :func:`kernel_error` measures (:func:`_hat_error`). Where ``D`` changes within the
    kernel the gathered error kernel ``G_p(delta) = E_{D(p - delta)}(delta)`` need not sum
    to 0: the mean radiance ``mu`` is rendered with a gain error ``g_p = sum_delta
    alpha(p - delta) G_p(delta)``, seen by no single-depth metric. For a smooth depth it is
    of second order, ``g = (1/2) |grad D|^2 d^2/dD^2`` of the second moment of ``E_D``: the
    true kernel's second moment is curved in ``D`` (quadratic for a pillbox, ``r ~ |D -
    D_focus|``) where the hat blend's is piecewise linear, so a depth slope brightens the
    truth and not the render unless representatives lie within the depths a kernel
    spans. At the image border (mirrored, as rendered) and at a kink of the depth it is of
    first order. On a rolling capture with depth down the rows the rows' mean errors were
    0.029, -0.025, ..., 0.011 (per unit contrast; predicted 0.025, -0.023, ..., 0.012) at
    1e-2, where the zero-mean estimate was 0.0079: the light of row 1 (and of its mirror
    image above row 0) reached row 0 through a kernel of the wrong size.

    ``g_p`` is computed at up to :data:`_GAIN_PIXELS` pixels of a band with the band's
    IPSFs: the true kernel of each inverse depth in their windows (beyond
    :data:`_GAIN_DEPTHS` depths, split linearly between that many nodes uniform in ``D``,
    as the brute-force reference does; the representatives added are then nodes, at most
    all of them). The estimate is ``mu sqrt(mean g_p^2) / contrast``
    (visible radiance), added in quadrature to the zero-mean part (the two are
    uncorrelated over textures). The sub-steps' scales and shifts are the magnification
    estimate's.
    """

    def __init__(self, scene: Scene, present: np.ndarray, half: int) -> None:
        self.present, self.half, self.shape = present, half, scene.shape
        radiance, inv = _visible(scene)
        contrast = _contrast(scene)
        self.ratio = float(np.mean(radiance[~np.isnan(inv)])) / contrast if contrast > 0 else 0.0
        widths = ((half, half), (half, half))
        self.maps = []
        for s in scene.surfaces:
            valid = s.alpha > 0
            idx = np.searchsorted(present, np.where(valid, 1.0 / s.depth_mm, present[0]))
            alpha = np.where(valid, s.alpha, 0.0)
            self.maps.append(
                (np.pad(idx, widths, mode="reflect"), np.pad(alpha, widths, mode="reflect"))
            )

    def error(self, r0, r1, layers, *, profile, cache: _KernelCache, near):
        """The band's estimated gain error and the inverse depth to add as a representative.

        Parameters
        ----------
        r0, r1 : int
            The band's rows ``[r0, r1)``.
        layers : tuple of Layer
            The band's hat layers.
        profile : Profile
            The band's exposure window.
        cache : _KernelCache
        near : ndarray
            The inverse depths whose blur reaches the band's rows.

        Returns
        -------
        (float, float or None)
            ``mu sqrt(mean g_p^2) / contrast`` over the band's sampled pixels, and the
            inverse depth (a true kernel's) whose light makes up most of ``g_p`` at the
            worst pixel (``None`` when each of those is a representative).
        """
        if self.ratio == 0:
            return 0.0, None
        reps = [layer.inv_rep for layer in layers]
        # the widest kernel: a near depth's blur is largest at an end of their range
        h = max(cache.kernel(float(d), profile).shape[0] for d in (near[0], near[-1], *reps)) // 2
        size, cols = 2 * h + 1, self.shape[1]
        n = max(1, min(_GAIN_PIXELS, _GAIN_BLOCK // size**2))
        step = math.ceil(math.sqrt((r1 - r0) * cols / n))
        rr, cc = np.meshgrid(
            np.arange(r0, r1, step), np.arange(step // 2, cols, step), indexing="ij"
        )
        dy, dx = np.mgrid[-h : h + 1, -h : h + 1]
        ys = rr.reshape(-1, 1, 1) + self.half - dy  # the source pixel p - delta (padded)
        xs = cc.reshape(-1, 1, 1) + self.half - dx
        windows = [(idx[ys, xs], alpha[ys, xs]) for idx, alpha in self.maps]
        used = np.unique(np.concatenate([w[a > 0] for w, a in windows]))
        if used.size == 0:
            return 0.0, None
        inv = self.present[used]
        ends = np.array([layer.inv_hi for layer in layers])
        lo, theta = composite._hat(inv, layers, np.searchsorted(ends, inv).clip(0, len(reps) - 1))
        nodes = inv if inv.size <= _GAIN_DEPTHS else np.linspace(inv[0], inv[-1], _GAIN_DEPTHS)
        if nodes.size > 1:
            j = (np.searchsorted(nodes, inv, side="right") - 1).clip(0, nodes.size - 2)
            w = np.clip((inv - nodes[j]) / (nodes[j + 1] - nodes[j]), 0.0, 1.0)
        else:
            j, w = np.zeros(inv.size, int), np.zeros(inv.size)
        top, j2 = np.minimum(lo + 1, len(reps) - 1), np.minimum(j + 1, nodes.size - 1)

        def grid(d):  # the kernel on the window (the widest kernel's size)
            k = cache.kernel(float(d), profile)
            return np.pad(k, (size - k.shape[0]) // 2)

        rendered = np.stack([grid(d) for d in reps])
        truth = np.stack([grid(d) for d in nodes])
        y, x = dy + h, dx + h
        gains, parts = 0.0, []
        for idx, alpha in windows:
            q = np.searchsorted(used, idx).clip(0, used.size - 1)  # alpha is 0 where absent
            e = (1 - theta[q]) * rendered[lo[q], y, x] + theta[q] * rendered[top[q], y, x]
            e -= (1 - w[q]) * truth[j[q], y, x] + w[q] * truth[j2[q], y, x]
            part = alpha * e
            gains = gains + part.sum(axis=(1, 2))
            parts.append((q, part))
        # the worst pixel's gain split between the true kernels' depths (nodes): the one
        # with the largest share, made a representative, is exact there
        worst, share = int(np.argmax(np.abs(gains))), np.zeros(nodes.size)
        for q, part in parts:
            q, part = q[worst].ravel(), part[worst].ravel()
            share += np.bincount(j[q], (1 - w[q]) * part, nodes.size)
            share += np.bincount(j2[q], w[q] * part, nodes.size)
        share[np.isin(nodes, reps)] = 0
        best = int(np.argmax(np.abs(share)))
        depth = float(nodes[best]) if share[best] != 0 else None
        return self.ratio * float(np.sqrt(np.mean(gains**2))), depth


def _blur_px(lens: Lens, inv: float, p_mm: np.ndarray) -> np.ndarray:
    v = optics.image_distance(lens.focal_length_mm, _depth(inv))
    return lens.blur_px(v, p_mm)


def _rep_weights(layers, inv: np.ndarray, weight: np.ndarray, hat: bool) -> np.ndarray:
    """Each layer representative's share of ``sum weight``: the pixels at inverse depths
    ``inv`` split as the renderer splits them (hat functions, or their box layer)."""
    ends = np.array([layer.inv_hi for layer in layers])
    idx = np.searchsorted(ends, inv, side="left").clip(0, len(layers) - 1)
    if not hat or len(layers) == 1:
        return np.bincount(idx, weight, len(layers))
    lo, theta = composite._hat(inv, layers, idx)
    return np.bincount(lo, weight * (1 - theta), len(layers)) + np.bincount(
        lo + 1, weight * theta, len(layers)
    )


def _magnification(profile, layers, lens, model, spectra, p_ref, shape, visible, r0, tol, *, hat):
    """Sub-steps for the magnification change ``p(t)/p_ref`` and the error of their shifts.

    Parameters
    ----------
    profile : Profile
        The band's exposure window of the motion.
    layers : tuple of Layer
        The band's depth layers.
    lens : Lens
    model : str
    spectra : _Spectra
    p_ref : float
    shape : tuple of int
        The image's rows and columns.
    visible : ndarray
        The inverse depth of the nearest surface at each pixel of the band's rows (NaN
        where none).
    r0 : int
        The band's first row.
    tol : float
    hat : bool
        Hat-function layers (else box layers).

    Returns
    -------
    (tuple of Step, float, bool, int)
        The sub-steps, the estimated RMS error over the band's pixels (in
        :func:`kernel_error` units), whether magnification is applied, the step count.

    Notes
    -----
    At time ``t`` the scene point seen at ``x`` (from the image centre) is displaced by
    ``delta(t) = (p(t) / p_ref - 1) x`` (Sec. 3, footnote 1). A sub-step renders its part
    of the exposure with its IPSF (Eq. 5) displaced by its mean ``delta``; over ``N``
    time nodes ``q`` the error at inverse depth ``D`` is
    ``E_D(w) = (1/N) sum_q K_q(D, w) (exp(-2 pi i w . (delta_q - mean_s delta)) - 1)``,
    ``K_q`` the lens PSF (Eq. 3 or 4) of node ``q``'s blur (Eq. 2). Its norm
    ``e_D(r)`` is computed at the image's RMS radius ``r``; for small displacements it is
    linear in ``|x|``, ``e_D(x) = e_D(r) |x| / |r|``. Away from depth edges each pixel's
    error is that of its own depth (the kernels are small against the scale over which
    the depth changes), so the band's mean squared error is the pixel mean of
    ``e_D(r)^2 |x|^2 / |r|^2``, not the largest ``e_D(r)``: a rolling-shutter row's window
    crosses the focus of only some of its depths (on the 48-row reference sweep the
    largest was up to 5x a row's measured error), and a row near the centre moves less
    than one at the top. ``e^2`` at a pixel's depth is that of the representatives it is
    rendered with, in the renderer's proportions (for a hat blend of two kernels the
    error of the blend is at most that mean, ``|.|^2`` being convex). The estimate is the
    expected error over 1/f textures; one texture's error scatters about it (on an 8x32
    px capture by about 25%).
    """
    t0, t1 = float(profile.times_s[0]), float(profile.times_s[-1])
    edges = np.linspace(t0, t1, _MAG_NODES + 1)
    t_mid = 0.5 * (edges[1:] + edges[:-1])
    p = profile.position(t_mid)
    radius = np.array([shape[1], shape[0]]) / math.sqrt(12)
    if np.ptp(p) == 0:  # static: one node
        p = p[:1]
    shifts = radius[None, :] * (p / p_ref - 1)[:, None]  # px at the RMS radius
    if np.max(np.abs(shifts)) < 1e-9:
        return (Step(profile, 1.0, 1.0),), 0.0, False, 1
    nodes = p.size
    y, x = np.indices(visible.shape)
    rho2 = (y + r0 - 0.5 * (shape[0] - 1)) ** 2 + (x - 0.5 * (shape[1] - 1)) ** 2
    seen = ~np.isnan(visible)
    weight = rho2[seen] / float(radius @ radius) / visible.size  # pixel mean of |x|^2/|r|^2
    share = _rep_weights(layers, visible[seen], weight, hat)
    reps = [(layers[i].inv_rep, float(share[i])) for i in np.flatnonzero(share > 0)]
    # sharpest first: a failing candidate usually fails there, and stops early
    reps.sort(key=lambda rw: float(_blur_px(lens, rw[0], p).min()))

    rasters = _Lru(48 << 20)  # the nodes' lens PSFs per representative, for every candidate

    def node_kernels(inv_rep: float) -> np.ndarray:
        if inv_rep not in rasters:
            blur = _blur_px(lens, inv_rep, p)
            half = psf.kernel_size(float(blur.max()), model=model, gaussian_g=lens.gaussian_g) // 2
            rasters[inv_rep] = np.stack(
                [psf.raster_lens_psf(model, b, half, lens.gaussian_g) for b in blur]
            )
        return rasters[inv_rep]

    def error(step_of_node, step_shift, stop=math.inf):
        total = 0.0
        for inv_rep, w in reps:
            kernels = node_kernels(inv_rep)
            moved = spectra.shifted_sum(kernels, shifts - step_shift[step_of_node])
            total += w * spectra.error((moved - spectra.of(kernels.sum(axis=0))) / nodes) ** 2
            if total > stop**2:
                break  # already above the tolerance: this candidate fails
        return math.sqrt(total)

    skip_error = error(np.zeros(nodes, int), np.zeros((1, 2)))
    if skip_error <= tol:
        return (Step(profile, 1.0, 1.0),), skip_error, False, 1
    n = 1
    while True:
        step_of_node = np.arange(nodes) * n // nodes
        step_shift = np.array([shifts[step_of_node == s].mean(axis=0) for s in range(n)])
        last = n >= min(MAX_MAGNIFICATION_STEPS, nodes)
        err = error(step_of_node, step_shift, math.inf if last else tol)
        if err <= tol or last:
            break
        n = min(2 * n, nodes)  # at most one step per time node: no empty steps
    return _steps(profile, p_ref, n), err, True, n


_NEIGHBOURS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dy, dx) != (0, 0)]


def _neighbour(a: np.ndarray, dy: int, dx: int, fill) -> np.ndarray:
    """``a`` shifted so that each pixel sees its ``(dy, dx)`` neighbour (``fill`` outside)."""
    p = np.pad(a, 1, mode="constant", constant_values=fill)
    r, c = a.shape
    return p[1 + dy : 1 + dy + r, 1 + dx : 1 + dx + c]


def _outline(alpha: np.ndarray) -> np.ndarray:
    """A surface's outline: its partly covered pixels and those with an uncovered neighbour."""
    valid = alpha > 0
    outside = np.zeros(alpha.shape, bool)
    for dy, dx in _NEIGHBOURS:
        outside |= ~_neighbour(valid, dy, dx, True)
    return valid & ((alpha < 1) | outside)


def _edges(scene: Scene, k: float) -> tuple[np.ndarray, float]:
    """Depth-edge pixels and the largest blur-radius jump (px) between neighbours.

    ``k = (a/2) p / pitch`` is the blur radius in px per unit inverse depth (Eq. 2). On one
    surface a pixel is an edge iff ``k max|D - D'|`` over its 8 neighbours exceeds 1: where
    the blur radius changes by less than 1 px per px, every ray through the aperture meets
    the surface exactly once (no self-occlusion, the plain sum of layers is exact). Between
    surfaces, the nearer surface's silhouette (alpha < 1 or a neighbour outside it) over a
    farther surface is an edge where ``k (D_near - D_far) > 0.5``.
    """
    mask = np.zeros(scene.shape, bool)
    worst = 0.0
    invs = []
    for s in scene.surfaces:
        valid = s.alpha > 0
        inv = np.where(valid, 1.0 / s.depth_mm, np.nan)
        invs.append(inv)
        jump = np.zeros(scene.shape)
        for dy, dx in _NEIGHBOURS:
            d = np.abs(inv - _neighbour(inv, dy, dx, np.nan))
            jump = np.fmax(jump, np.nan_to_num(d, nan=0.0))
        jump *= k
        worst = max(worst, float(jump.max()))
        mask |= valid & (jump > 1.0)
    for j, s in enumerate(scene.surfaces):
        rim = _outline(s.alpha)
        if not rim.any():
            continue
        for i in range(len(scene.surfaces)):
            if i == j:
                continue
            step = k * np.nan_to_num(invs[j] - invs[i], nan=0.0)
            hit = rim & (step > 0.5)
            if hit.any():
                worst = max(worst, float(step[hit].max()))
                mask |= hit
    return mask, worst


def _visible(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Radiance (channel mean) and inverse depth of each pixel's nearest surface with
    alpha > 0; NaN inverse depth where no surface covers the pixel."""
    order = sorted(
        range(len(scene.surfaces)), key=lambda i: float(np.median(scene.surfaces[i].depth_mm))
    )
    radiance = np.zeros(scene.shape)
    inv = np.full(scene.shape, np.nan)
    for i in order:  # nearest first
        s = scene.surfaces[i]
        m = (s.alpha > 0) & np.isnan(inv)
        radiance[m] = s.radiance[m].mean(axis=-1)
        inv[m] = 1.0 / s.depth_mm[m]
    return radiance, inv


def _contrast(scene: Scene) -> float:
    """RMS contrast of the visible radiance (nearest surface first, channel mean): the unit
    of the occlusion estimates. 0 for a uniform radiance: a standard deviation within
    1e-12 of the largest radiance is rounding (``np.std`` of 0.7s is 1.1e-16, not 0)."""
    radiance, inv = _visible(scene)
    filled = ~np.isnan(inv)
    if not filled.any():
        return 0.0
    std = float(np.std(radiance[filled]))
    return std if std > 1e-12 * float(np.max(np.abs(radiance[filled]))) else 0.0


def _edge_cells(scene: Scene, band: Band, cache: _KernelCache, edge: float, edge_mask, tol):
    """Time cells of sub-aperture compositing at the occluding edges, and its estimated error.

    Parameters
    ----------
    scene : Scene
    band : Band
        The plan's only band (global shutter), with its layers and sub-steps.
    cache : _KernelCache
        IPSF kernels (Eqs. 5-6) of the sub-steps.
    edge : float
        Inverse-depth gap beyond which a layer occludes another.
    edge_mask : ndarray of bool
        The scene's depth-edge pixels (:func:`_edges`).
    tol : float

    Returns
    -------
    (int, float) or None
        Time cells per sub-step and the estimated error, or ``None`` when the work
        (aperture cells x time cells x layers x px of the box around the edges) would
        exceed :data:`EDGE_WORK_BUDGET`: the plan then keeps 'over' compositing.

    Notes
    -----
    A static detector needs one time cell and is exact (the aperture cells follow the
    occluders' pixel lines, :mod:`pipeline.core.simulate.edge`). During a sweep
    the number ``n`` of time cells per sub-step doubles until the estimate is within
    ``tol``: the RMS change of the render from ``n`` to ``2n`` time cells (the layered
    part cancels), over the scene's RMS contrast, times 2: the error of ``n`` cells if it
    falls at least as ``1/n`` (on the reference edge sweeps it falls faster: the total
    estimates are 1.4-2.5x the measured errors).
    """
    lens = cache.lens
    reps = [layer.inv_rep for layer in band.layers]
    front = [d for d in reps if d > min(reps) + edge]  # layers that occlude another
    half = max(
        cache.kernel(d, st.profile, st.scale).shape[0] // 2 for d in reps for st in band.steps
    )
    rr, cc = np.nonzero(edge_mask.any(axis=1))[0], np.nonzero(edge_mask.any(axis=0))[0]
    box_px = (min(rr[-1] + 2 * half, scene.shape[0]) - max(rr[0] - 2 * half, 0)) * (
        min(cc[-1] + 2 * half, scene.shape[1]) - max(cc[0] - 2 * half, 0)
    )
    p_all = band.profile.image_distances_mm
    widest = [max(abs(edge_model.signed_radius(lens, d, p)) for p in p_all) for d in front]
    cells = len(edge_model.aperture_cells(widest)[0])
    work = len(band.steps) * cells * len(reps) * box_px
    moving = np.ptp(p_all) > 0
    if work * (2 if moving else 1) > EDGE_WORK_BUDGET:
        return None
    if not moving:
        return 1, 0.0
    contrast = _contrast(scene)

    def image(n):
        return sum(
            st.weight
            * composite.layered(scene, band.layers, st.profile, cache, True, edge, st.scale, n)
            for st in band.steps
        ).mean(axis=-1)

    n, coarse = 1, image(1)
    while True:
        fine = image(2 * n)
        est = 2 * float(np.sqrt(np.mean((fine - coarse) ** 2))) / contrast
        if est <= tol or 2 * n > MAX_EDGE_TIME_CELLS or 4 * n * work > EDGE_WORK_BUDGET:
            return n, est
        n, coarse = 2 * n, fine


def _occlusion_error(scene: Scene, camera: Camera, bands, p_ref: float) -> float:
    """Estimated error of 'over' compositing at the silhouettes of nearer surfaces.

    For each pair of surfaces (near over far) the exact straight-edge trace against the
    over model (:func:`pipeline.core.simulate.edge.edge_error`, with the two surfaces' own
    textures and their blur radii over the band's exposure, 16 time cells) gives the
    squared error per px of silhouette; the whole-image estimate is
    ``sqrt(sum L e / N) / contrast``. It is 0 where either side is in focus. Self-edges of
    one surface (depth steps in a depth map) are not counted.
    """

    lens = camera.lens
    rows, cols = scene.shape
    k = 0.5 * lens.aperture_mm * p_ref / lens.pixel_pitch_mm
    contrast = _contrast(scene)
    if contrast <= 0:
        return 0.0
    total = 0.0
    for j, near in enumerate(scene.surfaces):
        valid = near.alpha > 0
        rim = _outline(near.alpha)
        for i, far in enumerate(scene.surfaces):
            if i == j or not rim.any():
                continue
            hit = rim & (far.alpha > 0)
            inv_n = 1.0 / near.depth_mm[hit]
            inv_f = 1.0 / far.depth_mm[hit]
            if not hit.any() or k * np.median(inv_n - inv_f) <= 0.5:
                continue
            d_n, d_f = float(np.median(inv_n)), float(np.median(inv_f))
            # the straight edge through the silhouette's median column, near side left
            rr, cc = np.nonzero(hit)
            c = int(np.median(cc))
            tex_n, tex_f = near.radiance.mean(axis=-1), far.radiance.mean(axis=-1)
            if valid[:, : c + 1].sum() < valid[:, c:].sum():  # near side right: mirror
                tex_n, tex_f, c = tex_n[:, ::-1], tex_f[:, ::-1], cols - 1 - c
            r0 = max(0, min(int(np.median(rr)) - 32, rows - 64))
            tex_n, tex_f = tex_n[r0:], tex_f[r0:]
            worst = 0.0
            for band in bands:
                t0, t1 = float(band.profile.times_s[0]), float(band.profile.times_s[-1])
                cells = 1 if np.ptp(band.profile.image_distances_mm) == 0 else 16
                tb = np.linspace(t0, t1, cells + 1)
                p = band.profile.position(0.5 * (tb[1:] + tb[:-1]))
                d_p = 1.0 / lens.focal_length_mm - 1.0 / p
                err = edge_model.edge_error(
                    tex_n, tex_f, k * (d_n - d_p), k * (d_f - d_p), centre=c + 1
                )
                worst = max(worst, err)
            total += worst * int(np.count_nonzero(hit))
    return float(math.sqrt(total / (rows * cols)) / contrast)


def plan(
    scene: Scene,
    camera: Camera,
    *,
    tolerance: float = 1e-3,
    occlusion: bool | None = None,
    magnification_steps: int | None = None,
    per_row: bool = False,
) -> Plan:
    """Decide which effects a capture of ``scene`` needs at ``tolerance`` (see module notes).

    Parameters
    ----------
    scene : Scene
    camera : Camera
    tolerance : float
        Largest acceptable :func:`kernel_error` of any approximation (default 1e-3).
    occlusion : bool, optional
        Force occlusion compositing on/off (default: on iff the scene has depth edges).
    magnification_steps : int, optional
        Force this many magnification sub-steps (0: ignore magnification).
    per_row : bool
        Rolling shutter: render every row with its own window (no banding).

    Returns
    -------
    Plan
    """
    if not isinstance(scene, Scene):
        raise InputError(f"scene must be a pipeline.core.scene.Scene, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise InputError(
            f"camera must be a pipeline.core.scene.Camera, got {type(camera).__name__}"
        )
    if not (isinstance(tolerance, (int, float)) and 0 < tolerance < 1):
        raise InputError(f"tolerance must be in (0, 1), got {tolerance!r}")
    lens, model = camera.lens, camera.model
    rows, cols = scene.shape
    present = _present_inverse_depths(scene, lens)
    p_all = camera.motion.image_distances_mm
    max_blur = max(float(_blur_px(lens, d, p_all).max()) for d in (present[0], present[-1]))
    size = psf.kernel_size(max_blur, model=model, gaussian_g=lens.gaussian_g)
    if size > psf.MAX_KERNEL_SIZE:
        raise InputError(
            f"the blur reaches {max_blur:.0f} px ({size} px kernel > {psf.MAX_KERNEL_SIZE}); "
            "use a coarser pixel pitch (a downscaled lens profile) or a smaller aperture"
        )
    spectra = _Spectra(_grid(size))
    cache = _KernelCache(lens, model, spectra)
    finite = _finite_scene_factor((rows, cols), spectra.n)  # kernel_error -> image error
    effects = []
    if scene.missing_pixels:
        what = (
            "given the nearest valid depth"
            if scene.missing_depth == "fill"
            else "excluded (zero radiance and alpha)"
        )
        effects.append(Effect("missing depth", True, f"{scene.missing_pixels} px {what}", 0.0))

    # Rolling shutter: bands of rows whose IPSFs agree within the tolerance.
    windows = camera.row_windows(rows)
    profiles = [camera.motion] if camera.effective_shutter == "global" else None
    if profiles is None:
        row_profiles: dict[int, Profile] = {}

        def row_profile(r: int) -> Profile:
            if r not in row_profiles:
                row_profiles[r] = camera.motion.window(*windows[r])
            return row_profiles[r]

        q = np.unique(np.quantile(present, np.linspace(0, 1, _CHECK_DEPTHS)))

        def row_dist(a, b):
            pa, pb = row_profile(int(a)), row_profile(int(b))
            return max(spectra.error(cache.spectrum(d, pa) - cache.spectrum(d, pb)) for d in q)

        all_rows = np.arange(rows)
        if per_row:
            parts, band_err = [(r, r) for r in range(rows)], 0.0
        else:
            parts, band_err, _ = _partition(
                all_rows, 0, rows - 1, row_dist, tolerance, integer=True
            )
            band_err *= finite
        starts = [0] + [end + 1 for end, _ in parts[:-1]]
        band_specs = [(s, end + 1, row_profile(rep)) for s, (end, rep) in zip(starts, parts)]
        if len(parts) == 1:
            effects.append(
                Effect(
                    "rolling-shutter rows",
                    False,
                    "every row's IPSF is within the tolerance of the middle row's: one band",
                    band_err,
                )
            )
        else:
            effects.append(
                Effect(
                    "rolling-shutter rows",
                    True,
                    f"{len(parts)} bands of rows, each with its own exposure window",
                    band_err,
                )
            )
    else:
        band_specs = [(0, rows, camera.motion)]
        effects.append(Effect("rolling-shutter rows", False, "global shutter", 0.0))

    visible = _visible(scene)[1]
    a_p = lens.aperture_mm * float(p_all.max()) / lens.pixel_pitch_mm  # d b_px / d D (Eq. 2)
    edge = EDGE_BLUR_PX / a_p
    edge_mask, jump = _edges(scene, 0.5 * a_p)
    n_edge = int(np.count_nonzero(edge_mask))
    if occlusion is None:
        occlusion = n_edge > 0
    p_ref = camera.reference_mm
    groups = _groups(scene, present)
    # rows whose pixels reach a band's rows: the largest blur plus the magnification shift
    moved = 0.5 * math.hypot(rows, cols) * float(np.max(np.abs(p_all / camera.reference_mm - 1)))
    reach = size // 2 + math.ceil(moved) + 1
    gain = None if occlusion else _Gain(scene, present, size // 2)
    bands, layer_sq, mag_sq, mag_applied, mag_steps = [], 0.0, 0.0, False, 1
    for r0, r1, prof in band_specs:
        cache.clear()  # a fresh cache per band: memory does not grow with the rows
        near = _near(scene, max(0, r0 - reach), r1 + reach)
        band_gain = None
        if gain is not None:
            band_gain = functools.partial(gain.error, r0, r1, profile=prof, cache=cache, near=near)
        layers, err, checks, g_err = _layers(
            groups, near, prof, cache, tolerance, hat=not occlusion, gain=band_gain
        )
        if magnification_steps is None:
            steps, m_err, m_app, n = _magnification(
                prof, layers, lens, model, spectra, p_ref, (rows, cols), visible[r0:r1], r0,
                tolerance, hat=not occlusion,
            )
        else:
            steps, m_err, m_app, n = _forced_steps(prof, p_ref, magnification_steps)
        mag_applied, mag_steps = mag_applied or m_app, max(mag_steps, n)
        if not occlusion:  # else box layers (occlusion compositing): _layers' own error
            err = _hat_error(groups, near, layers, checks, steps, cache, (rows, cols))
        # each band's estimate bounds the RMS error of its rows: the image's RMS error is
        # at most their row-weighted RMS (not their maximum, 2x looser over a rolling sweep);
        # the gain error (image units) is uncorrelated with the zero-mean part
        layer_sq += (r1 - r0) * ((finite * err) ** 2 + g_err**2)
        mag_sq += (r1 - r0) * m_err**2
        bands.append(Band(r0, r1, prof, layers, steps))
    layer_err = math.sqrt(layer_sq / rows)
    mag_err = finite * math.sqrt(mag_sq / rows)
    n_layers = max(len(b.layers) for b in bands)
    span = f"{_depth(present[-1]):.6g}-{_depth(present[0]):.6g} mm"
    if n_layers == 1:
        reason = f"the whole depth range ({span}) is within the tolerance of one kernel"
    else:
        reason = f"{n_layers} layers over {span}, split in inverse depth by kernel_error"
        reason += (
            " (box layers: occlusion compositing)"
            if occlusion
            else "; hat-function interpolation, error checked over the sub-steps and for the "
            "mean radiance where the depth changes within a kernel"
        )
    effects.append(Effect("depth layers", n_layers > 1, reason, layer_err))
    corner_px = 0.5 * math.hypot(rows - 1, cols - 1) * float(np.max(np.abs(p_all / p_ref - 1)))
    if mag_applied:
        reason = (
            f"image moves up to {corner_px:.3g} px at the corner (p/p_ref, "
            f"p_ref={p_ref:.6g} mm): {mag_steps} scaled sub-step(s)"
        )
    else:
        reason = f"image moves up to {corner_px:.3g} px at the corner: below the tolerance"
    effects.append(Effect("magnification", mag_applied, reason, mag_err))

    time_cells = 0
    if n_edge == 0:
        reason = (
            f"no depth edges (the blur radius changes by at most {jump:.3g} px per px; "
            "every ray meets the scene once): plain sum of layers"
        )
        est = 0.0
    else:
        reason = (
            f"{n_edge} px on depth edges (the blur radius jumps up to {jump:.3g} px): "
            "back-to-front 'over' compositing"
        )
        est = float(max(np.max(s.radiance) for s in scene.surfaces))
        if occlusion:
            est = _occlusion_error(scene, camera, bands, p_ref)
            cells = None
            if est > tolerance and len(bands) == 1 and model == "pillbox":
                cells = _edge_cells(scene, bands[0], cache, edge, edge_mask, tolerance)
            if cells is not None:
                time_cells, est = cells
                reason += (
                    f"; sub-aperture compositing near the edges ({time_cells} time cell(s) "
                    "per sub-step) for partial occlusion"
                )
            elif est > 0:
                reason += ": partial occlusion at the silhouettes is not modelled"
    effects.append(Effect("occlusion", occlusion, reason, est))

    if camera.exposure is None:
        effects.append(Effect("noise", False, "no exposure level given", 0.0))
    else:
        e = camera.exposure
        effects.append(
            Effect(
                "noise",
                True,
                f"Poisson shot noise at {e.electrons_at_unit:g} e-/unit radiance + "
                f"{e.read_noise_e:g} e- read noise",
                0.0,
            )
        )
    return Plan(
        tolerance=float(tolerance),
        shape=(rows, cols),
        lens=lens,
        model=model,
        bands=tuple(bands),
        occlusion=bool(occlusion),
        edge_inv_depth=edge,
        noise=camera.exposure,
        effects=tuple(effects),
        edge_time_cells=time_cells,
    )


def _forced_steps(profile: Profile, p_ref: float, n: int):
    validate.whole("magnification_steps", n, minimum=0)
    if n == 0:
        return (Step(profile, 1.0, 1.0),), 0.0, False, 1
    return _steps(profile, p_ref, n), 0.0, True, n


def _steps(profile: Profile, p_ref: float, n: int) -> tuple[Step, ...]:
    """``n`` equal-time sub-steps, each scaled by its mean ``p / p_ref``."""
    t0, t1 = float(profile.times_s[0]), float(profile.times_s[-1])
    bounds = np.linspace(t0, t1, n + 1)
    steps = []
    for a, b in itertools.pairwise(bounds):
        window = profile.window(float(a), float(b)) if n > 1 else profile
        steps.append(Step(window, mean_position(window) / p_ref, (b - a) / (t1 - t0)))
    return tuple(steps)
