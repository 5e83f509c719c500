"""What the aligned frames support: a restored focal stack kept within the frames' range
and, where one frame shows more detail than the restoration, that frame (issue 13).

The paper's model (Eqs. 5-6) is linear and depth-invariant; real stacks break it at
occlusion edges, at the ends of the focus range (Sec. 4.1) and where the fitted blur
is not the lens's. Where they do, deconvolution leaves what the frames can explain:
rims and dark moats (values outside every frame's), or a softer result than the frame
focused there. A true all-in-focus image is, at each pixel, one of the frames (the one
in focus there), so

* it never leaves ``[min, max]`` of the frames near that pixel, in each channel and in
  colour (:func:`clip_to_frames`; a 3x3 neighbourhood is the registration slack), and
* where the sharpest frame holds more local contrast than the restoration, above the
  noise, the frame is the better estimate (:func:`prefer_sharpest`).

The per-pixel range and the sharpest frame are streamed beside the weighted sum
(:class:`FrameSupport`, merged like the sum), so memory stays flat in the frame count.
Wiener's noise is also held to a share of one frame's (:func:`noise_ceiling`).

The clip, after :func:`quiet_flat_areas` (where every frame is flat, the result's fine
band comes from the average), is the main job's default: only the range is streamed for
it; ``--no-frame-range`` turns both off. On the four real stacks of issue 13 they took
the regions as good as focus-stack's on every measure from 0/0/0/0 to 0/8/4/7 of 9 (halo
losses 27 -> 0 of 36, flat-area noise losses 34 -> 0), and on stacks that follow the
paper's model they cost at most 0.01 dB (+0.1-0.4 dB on the three-plane scenes). The
rest is ``flexdof stack --frame-guard``: 6-8 of 9 regions on the real stacks, but on
stacks that follow the model up to 3.0 dB below the default (4.3 dB with a fitted, doubled
blur span) and 1.2-1.4x the time (``tests/benchmarks/results/real_regions/NOTE.md``).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from pipeline.core.colour import scale_channels
from pipeline.core.deconvolve.common import noise_sigma_2d

# smoothing of the squared Laplacian (the per-pixel focus measure): wide enough that
# the flat inside of a stripe takes the frame its edges choose (at 2 px the choice
# there followed noise: blotches of defocused frames on pcb7's barcode)
FOCUS_SIGMA_PX = 8.0
FOCUS_BLOCK_PX = 4  # the focus measure and the frame choice are per block of this side
# (sigma, window) px of the detail bands compared: g - G_sigma * g, std over the window
DETAIL_BANDS = ((1.0, 7.0), (4.0, 15.0))
BLEND_SIGMA_PX = 6.0  # smoothing of the blend map: no seams at its edges
ENERGY_BLOCK_PX = 4  # the blend weights are computed per block of this side
CONTRAST_FLOOR = 2.0 / 255.0  # detail std (display levels of 8-bit sRGB) below which no swap
# The range and the sharpest frame are kept as 16-bit codes of [0, 1] linear light
# (nearest rounding, 1.5e-5 steps; a third of float32's memory and fast integer
# min/max). The end codes mean "at or beyond": a range bound there is open.
CODE_MAX = 65535
# a code added to every channel by cv2.add / cv2.subtract (a bare number changes only the
# first channel under OpenCV 4's Python bindings: opencv/opencv#24057)
ONE_CODE = (1.0, 1.0, 1.0, 1.0)
_WHITE = (1.0, 1.0, 1.0, 1.0)  # white in every channel, for the same reason
# rounds of the colour's two bounds, each kept in turn at a kept sum: one round left 0.9%
# of random pixels out of the ratios' range by up to 0.07; two leave none out by more than
# two codes (tests/test_frame_support.py)
COLOUR_ROUNDS = 2
CLIP_STRIP_ROWS = 256  # rows per strip of the clip (a strip's bounds: 2 x 6 MB at 2048 px RGB)


def to_codes(image: np.ndarray) -> np.ndarray:
    """``round(image * 65535)`` saturated to uint16: values beyond 1 (and infinity) are
    capped first, negative ones give 0, a NaN (nothing known) the end code 65535.

    The product is taken in the image's precision (float32 for frames) and rounded half to
    even: the bits of OpenCV 5.1's ``cv2.multiply(image, 65535, dtype=CV_16U)`` (checked
    on 20 Mpx of uniform values and on every half code and its neighbours), in half its
    time (1.2 against 2.3 ms on 256 rows of 2048 px RGB: OpenCV's scaled conversion to 16
    bits has no fast path), whatever OpenCV is installed (OpenCV 5.0 took the product in
    double). In float32 a product within half an ulp (2**-9 code) of a half code may round
    to either side of it, so a code is at most 0.502 codes off.
    """
    # the cap is a full-frame copy (8 ms on 3 Mpx RGB); decoded frames never exceed 1
    # (a 1 ms check), and a NaN maximum takes the capping path
    if not np.max(image) <= 1.0:
        image = np.nan_to_num(np.minimum(image, np.float32(1.0), dtype=np.float32), nan=1.0)
    dtype = np.float64 if image.dtype == np.float64 else np.float32
    with np.errstate(over="ignore"):  # -1e38 * 65535 is -inf: code 0, as it should be
        product = np.multiply(image, dtype(CODE_MAX), dtype=dtype)
    np.rint(product, out=product)
    np.clip(product, 0, CODE_MAX, out=product)
    return product.astype(np.uint16)


def from_codes(codes: np.ndarray) -> np.ndarray:
    """Linear float32 values of 16-bit codes: ``code / 65535`` rounded to float32 (the bits
    of OpenCV's ``cv2.multiply(codes, 1 / 65535, dtype=CV_32F)``, checked on every code, in
    a ninth of its time: 0.5 against 4.3 ms on 256 rows of 2048 px RGB)."""
    return np.divide(codes, np.float32(CODE_MAX), dtype=np.float32)


# added to each channel before the chromaticity is taken (linear light): a black pixel
# reads grey, not 0/0 (2e-4 is under one 8-bit sRGB level)
CHROMA_FLOOR = 2e-4


def colour_codes(image: np.ndarray) -> np.ndarray:
    """16-bit codes (rows, cols, 4) of an RGB image's colour: its chromaticity ``(R, B) /
    (R + G + B)``, each channel raised by ``CHROMA_FLOOR`` (neutral at 1/3), then its colour
    differences ``(R - G + 1) / 2`` and ``(B - G + 1) / 2`` (linear light). By strips of
    ``CLIP_STRIP_ROWS`` with OpenCV, one channel at a time (0.013 s on 3 Mpx: a ninth of
    numpy's time, a sixth of ``cv2.transform``'s into two and four channels; a strip's
    worth of float temporaries).

    The two pairs bound a colour where the other cannot: the ratio at dark pixels (a dark
    pixel with a bright one's difference is far more saturated than it), the difference
    at bright ones (a bright pixel with a dark one's ratio is: beside pcb10's highlights,
    cream frames and gold ones, a result of the cream's brightness in the gold's
    chromaticity read saturated yellow).
    """
    out = np.empty((*image.shape[:2], 4), np.uint16)
    floor, top = float(CHROMA_FLOOR), float(CODE_MAX)
    for r0 in range(0, image.shape[0], CLIP_STRIP_ROWS):
        strip = np.ascontiguousarray(image[r0 : r0 + CLIP_STRIP_ROWS], dtype=np.float32)
        red, green, blue = cv2.split(strip)
        total = cv2.add(cv2.add(cv2.add(red, green), blue), 3.0 * floor)
        cv2.merge([
            cv2.divide(cv2.add(red, floor), total, scale=top, dtype=cv2.CV_16U),
            cv2.divide(cv2.add(blue, floor), total, scale=top, dtype=cv2.CV_16U),
            cv2.addWeighted(red, 0.5 * top, green, -0.5 * top, 0.5 * top, dtype=cv2.CV_16U),
            cv2.addWeighted(blue, 0.5 * top, green, -0.5 * top, 0.5 * top, dtype=cv2.CV_16U),
        ], dst=out[r0 : r0 + CLIP_STRIP_ROWS])  # straight into the output's rows
    return out


@dataclasses.dataclass
class FrameSupport:
    """Streaming per-pixel statistics of aligned frames (linear light, unweighted).

    Attributes
    ----------
    low, high : ndarray (rows, cols[, c]), uint16
        Per-pixel minimum and maximum over the frames, as codes (:func:`to_codes`).
    focus : ndarray, float32
        The best focus measure seen, per block (:func:`focus_measure`).
    sharpest : ndarray like ``low``
        Per block, the frame with the best focus measure (codes).
    noise : list of ndarray
        Each frame's noise std per channel (:func:`frame_noise`).
    colour_low, colour_high : ndarray (rows, cols, 4), uint16, or None
        Per-pixel minimum and maximum over the frames of their colour
        (:func:`colour_codes`: chromaticity and colour differences); ``None`` for frames
        that are not RGB.
    """

    low: np.ndarray
    high: np.ndarray
    focus: np.ndarray
    sharpest: np.ndarray
    noise: list
    colour_low: np.ndarray | None = None
    colour_high: np.ndarray | None = None

    @classmethod
    def of_frame(cls, frame: np.ndarray, valid: np.ndarray, *, full: bool = True) -> FrameSupport:
        """The statistics of one frame (``valid``: its pixels not clipped). Without
        ``full``, only its range and noise, the noise on a ``LIMIT_NOISE_CROP_PX`` crop
        (``focus`` and ``sharpest`` ``None``): all that :func:`clip_to_frames` and
        :func:`visible_noise_limit` need."""
        codes = to_codes(frame)  # one array for all three until a merge writes
        rgb = frame.ndim == 3 and frame.shape[2] == 3
        colour = colour_codes(frame) if rgb else None
        if not full:
            noise = [frame_noise(frame, valid, LIMIT_NOISE_CROP_PX)]
            return cls(codes, codes, None, None, noise, colour, colour)
        noise = [frame_noise(frame, valid)]
        return cls(codes, codes, focus_measure(codes), codes, noise, colour, colour)

    def add_frame(self, frame: np.ndarray, valid: np.ndarray) -> FrameSupport:
        """Fold one more frame into range-only statistics, in place: the same as
        ``self.merge(FrameSupport.of_frame(frame, valid, full=False))``, but by strips of
        ``CLIP_STRIP_ROWS`` rows, each strip's codes folded in while in cache, without the
        frame's own full-size code arrays (pcb7: 12 + 25 MB a frame, made and then folded
        in)."""
        if self.focus is not None:
            raise ValueError("add_frame folds range-only statistics (full=False) only")
        folds = [(self.low, self.high, to_codes)]
        if frame.ndim == 3 and frame.shape[2] == 3 and self.colour_low is not None:
            folds.append((self.colour_low, self.colour_high, colour_codes))
        bounds = []
        for low, high, codes_of in folds:
            # a single frame's statistics share one array: the maxima go to a new one
            new_high = np.empty_like(low) if high is low else high
            low_rows, high_rows, new_rows = (_by_rows(a) for a in (low, high, new_high))
            for r0 in range(0, frame.shape[0], CLIP_STRIP_ROWS):
                rows = slice(r0, r0 + CLIP_STRIP_ROWS)
                codes = _by_rows(codes_of(frame[rows]))
                cv2.max(high_rows[rows], codes, dst=new_rows[rows])  # before the minimum
                cv2.min(low_rows[rows], codes, dst=low_rows[rows])
            bounds.append(new_high)
        self.high = bounds[0]
        if len(bounds) > 1:
            self.colour_high = bounds[1]
        self.noise = [*self.noise, frame_noise(frame, valid, LIMIT_NOISE_CROP_PX)]
        return self

    def merge(self, other: FrameSupport) -> FrameSupport:
        """Fold ``other`` in, in place (on a tie of focus ``self``'s frame stays: the
        result depends on the frames' order into the merges, which is fixed)."""
        shared = self.high is self.low  # a single frame's statistics share one array
        if shared and self.sharpest is not None:
            self.sharpest = self.low.copy()
        # OpenCV, not numpy: multi-threaded, without the GIL beside the other lane, and
        # a masked copy with one mask for all channels (np.copyto's broadcast ``where``
        # took 20 ms a frame on 3 Mpx RGB, cv2.copyTo 1.5 ms). A shared bound's maximum
        # goes to a new array before the minimum overwrites it: no copy first (a lane's
        # first merge copied 3 Mpx of codes and of colour codes, 12 + 28 ms, faulting in
        # fresh pages)
        self.high = cv2.max(self.high, other.high, dst=None if shared else self.high)
        cv2.min(self.low, other.low, dst=self.low)
        if self.colour_low is not None and other.colour_low is not None:
            shared = self.colour_high is self.colour_low
            self.colour_high = cv2.max(
                self.colour_high, other.colour_high, dst=None if shared else self.colour_high
            )
            cv2.min(self.colour_low, other.colour_low, dst=self.colour_low)
        # every frame's noise, the range-only statistics' too (before stop 42 they kept
        # only the first frame's: the noise limit read frame 0's, not the frames' median)
        self.noise = self.noise + other.noise
        if self.focus is None:  # the range only
            return self
        better = cv2.compare(_choice(other.focus - self.focus, self.sharpest.shape), 0, cv2.CMP_GT)
        cv2.copyTo(other.sharpest, better, self.sharpest)
        np.maximum(self.focus, other.focus, out=self.focus)
        return self

    def median_noise(self) -> np.ndarray:
        """The frames' median noise std per channel."""
        return np.median(np.array(self.noise, dtype=np.float64), axis=0)


def _by_rows(codes: np.ndarray) -> np.ndarray:
    """A view of a code array as OpenCV returns one: (rows, cols) for a single channel,
    (rows, cols, c) otherwise (a (rows, cols, 1) frame's codes come back 2-D)."""
    flat = codes.reshape(codes.shape[0], codes.shape[1], -1)
    return flat[..., 0] if flat.shape[2] == 1 else flat


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _reduced(image: np.ndarray, factor: int) -> np.ndarray:
    """Box average over ``factor x factor`` blocks (the last partial block included)."""
    rows, cols = image.shape[:2]
    size = (-(-cols // factor), -(-rows // factor))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _choice(difference: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A per-block focus difference interpolated (bilinear, block centres) to ``shape``
    (rows, cols): its sign picks a frame per pixel, with boundaries that follow the
    focus measure instead of the 4 px block grid (a staircase of seams otherwise)."""
    rows, cols = difference.shape
    full = cv2.resize(difference, (cols * FOCUS_BLOCK_PX, rows * FOCUS_BLOCK_PX),
                      interpolation=cv2.INTER_LINEAR)
    return full[: shape[0], : shape[1]]


def focus_measure(frame: np.ndarray) -> np.ndarray:
    """Local energy of the Laplacian of the grey frame, ``sqrt(G_8px * (lap g)^2)``, per
    ``FOCUS_BLOCK_PX`` block (the frame's size divided by it, rounded up).

    The usual focus measure of focus stacking (Nayar & Nakagawa's sum-modified
    Laplacian family): in focus, fine detail and so the Laplacian's energy peak. The
    energy is smoothed over 8 px anyway, so a block of 4 px loses nothing and costs a
    sixteenth of the time and memory. Any scale of ``frame`` (codes) will do: only
    the frames' order at each block counts.
    """
    lap = cv2.Laplacian(_grey(frame), cv2.CV_32F, ksize=3)
    energy = _reduced(np.square(lap, out=lap), FOCUS_BLOCK_PX)
    energy = cv2.GaussianBlur(energy, (0, 0), FOCUS_SIGMA_PX / FOCUS_BLOCK_PX)
    return np.sqrt(np.maximum(energy, 0.0))


NOISE_CROP_PX = 1024  # centre crop the frame guard's per-frame noise estimate reads
# ... and the default's (the noise limit's), read on every frame as it is summed: a
# quarter of the pixels (pcb7: 15 against 59 ms a frame; at 1024 px it added 0.2 s, 36%,
# to pcb7's accumulation)
LIMIT_NOISE_CROP_PX = 512


def frame_noise(frame: np.ndarray, valid: np.ndarray, crop_px: int = NOISE_CROP_PX) -> np.ndarray:
    """Noise std per channel of a frame, on a centre crop of ``crop_px``, by the estimator
    Wiener uses on the average (:func:`pipeline.core.deconvolve.common.noise_sigma_2d`: the
    lower of the Haar and spectral bounds), so the two are comparable (the Haar bound alone
    reads a clean frame's fine texture as noise: 4e-4 on a clean synthetic stack, which
    then held Wiener 6 dB below its clean result)."""
    r0 = max(0, (frame.shape[0] - crop_px) // 2)
    c0 = max(0, (frame.shape[1] - crop_px) // 2)
    crop = (slice(r0, r0 + crop_px), slice(c0, c0 + crop_px))
    channels = frame[..., None] if frame.ndim == 2 else frame
    ok = valid[crop]
    return np.array(
        [noise_sigma_2d(channels[(*crop, c)], ok) for c in range(channels.shape[2])]
    )


NOISE_SHARE = 0.7  # the result may be at most this fraction of a single frame's noise
# ... but never held below this std (linear light): a quarter of an 8-bit level in deep
# shadow (linear 0.02), invisible; clean synthetic frames (noise ~0) are not regularised
NOISE_FLOOR = 2e-4


def frame_noise_ceiling(support: FrameSupport) -> np.ndarray:
    """The restored image's noise std ceiling per channel: ``NOISE_SHARE`` of a frame's.

    Wiener's natural-prior fit sets ``lam = sigma^2 / s2`` with ``s2`` inversely
    proportional to ``sum(k^2)``, which collapses for the wide IPSFs of real stacks
    (white-noise gains of 30+ on pcb10: grain and ringing). An all-in-focus image needs
    no more noise than the frame focused at each pixel, so the filter is held to a
    share of one frame's noise (measured on the warped frames, so JPEG's correlated noise
    and the average's real noise reduction are in the ratio), floored at ``NOISE_FLOOR``.
    """
    return np.maximum(NOISE_SHARE * support.median_noise(), NOISE_FLOOR)


def noise_ceiling(support: FrameSupport, average: np.ndarray, clipped) -> np.ndarray | None:
    """:func:`frame_noise_ceiling` where the frames' noise is noise, else ``None``.

    ``average`` is the frames' weighted average (``clipped``: its pixels clipped in some
    frame), read by :func:`frame_noise` on the same crop as the frames.

    Averaging independent frames lowers noise, so a frame reads noisier than the average
    (pcb7: 1.1-1.5x, pcb10 2.7x; sigma 0.01 on 9 synthetic frames: 3x). Where it does not
    (a clean synthetic stack: the frame 5e-4, the average 1.2e-3), both estimates read
    texture, not noise, and the ceiling would only blur: none is set.
    """
    frame = support.median_noise()
    if not np.all(frame > frame_noise(average, ~clipped)):
        return None
    return frame_noise_ceiling(support)


VISIBLE_NOISE = 0.006  # linear light: 1.7 levels of 8-bit sRGB at mid-grey (linear 0.18)


def visible_noise_limit(
    support: FrameSupport, average: np.ndarray, clipped
) -> np.ndarray | None:
    """The default Wiener result's noise std limit per channel, or ``None``.

    ``max(VISIBLE_NOISE, a frame's noise)``, set where the frames read noisier than their
    average (so their noise is noise, see :func:`noise_ceiling`): a result may be as noisy
    as the frame focused at each pixel (the peer's composite is), or as noisy as a grain
    under about two 8-bit levels, but not more. The Wiener filter applies it only where
    its gain ceiling set ``lam`` (``noise_limit`` of
    :func:`pipeline.core.deconvolve.wiener._plan_wiener`), and there it binds only on
    noisy frames: the average's noise estimate times ``MAX_NOISE_GAIN`` (10) stays under
    ``VISIBLE_NOISE`` on pcb7, pcb10 and beetle as shot (0.0054, 0.0023, 0.0014 in G).
    It binds on amber (0.0011 in G: gain 5.6, its region count unchanged) and on pcb7 at
    ISO 3200 (0.0021: gain 2.8, lam 13x the floor; 0/9 regions against focus-stack
    became 5/9; issue 13). Unlike the frame guard's :func:`frame_noise_ceiling` it also
    holds GCV's ``lam``, whose residual on real stacks is mostly kernel mismatch.
    """
    frame = support.median_noise()  # on LIMIT_NOISE_CROP_PX crops (range-only statistics)
    if not np.all(frame > frame_noise(average, ~clipped, LIMIT_NOISE_CROP_PX)):
        return None
    return np.maximum(frame, VISIBLE_NOISE)


def _channels(image: np.ndarray) -> list[np.ndarray]:
    """Views of each channel of an image (the image itself when it is 2-D)."""
    return [image] if image.ndim == 2 else [image[..., c] for c in range(image.shape[2])]


def clip_to_frames(
    image: np.ndarray, support: FrameSupport, clipped=None, *, radius_px: int = 1
) -> np.ndarray:
    """``image`` clipped, per pixel and channel, to the frames' range over a
    ``(2 radius + 1)^2`` neighbourhood (the registration slack), in place.

    The 16-bit codes round to nearest, so the range is widened by one code; the lower
    bound is never below 0 (light is not negative), an upper bound at the end code
    65535 is open (frames at or beyond white), and pixels ``clipped`` in some frame keep
    no upper bound (the frames saw only that the scene is at least that
    bright). An RGB image is then kept to the frames' range of displayed colour as well
    (:func:`_clip_colour`; where ``support`` has it). By strips of
    ``CLIP_STRIP_ROWS`` rows (all channels at once, with OpenCV's threaded min/max: 90 ->
    25 ms on pcb10's 3 Mpx), so the bounds' float temporaries stay a strip's worth.
    """
    r = int(radius_px)
    box = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1, 2 * r + 1))
    lows, highs = support.low.reshape(image.shape), support.high.reshape(image.shape)
    colour = support.colour_low is not None and image.ndim == 3 and image.shape[2] == 3
    colour_lows, colour_highs = support.colour_low, support.colour_high
    rows = image.shape[0]
    for r0 in range(0, rows, CLIP_STRIP_ROWS):
        r1 = min(rows, r0 + CLIP_STRIP_ROWS)
        a0, a1 = max(0, r0 - r), min(rows, r1 + r)  # the strip and its neighbourhood's rows
        inner = slice(r0 - a0, r0 - a0 + r1 - r0)
        low_codes = cv2.erode(lows[a0:a1], box, borderType=cv2.BORDER_REPLICATE)[inner]
        high_codes = cv2.dilate(highs[a0:a1], box, borderType=cv2.BORDER_REPLICATE)[inner]
        # one code in every channel (``ONE_CODE``); 0 stays 0: light is never negative
        low = from_codes(cv2.subtract(low_codes, ONE_CODE))
        high = from_codes(cv2.add(high_codes, ONE_CODE))
        at_white = high_codes == CODE_MAX
        np.putmask(high, at_white, np.inf)
        if clipped is not None:
            high[clipped[r0:r1]] = np.inf
        out = image[r0:r1]
        cv2.max(out, low, dst=out)
        cv2.min(out, high, dst=out)
        if colour:
            colour_low = cv2.erode(colour_lows[a0:a1], box, borderType=cv2.BORDER_REPLICATE)
            colour_high = cv2.dilate(colour_highs[a0:a1], box, borderType=cv2.BORDER_REPLICATE)
            _clip_colour(out, colour_low[inner], colour_high[inner], low, high)
    return image


def _clip_colour(out, low_codes, high_codes, low, high) -> None:
    """Keep the RGB strip ``out``'s displayed colour (:func:`colour_codes` of ``out``
    capped at white) within the frames' range (codes over the neighbourhood), each moved
    pixel keeping its capped sum ``R + G + B``: first its chromaticity, then its colour
    differences; then ``out`` is clipped to the channels' range ``[low, high]`` again,
    and a channel the rebuild leaves at or beyond white keeps its value beyond. In place.
    The pixels are compared as codes made by the frames' own function, so a frame's
    colour always passes: no code of slack.

    The per-channel range alone admits colours no frame shows: beside a clipped highlight
    each channel's deconvolution undershoots by its own amount, so a pixel may take the
    frames' highest red and their lowest green and blue (orange and red rims on pcb7's
    pins; yellow ones beside pcb10's white pads; 0.1-1.4% of the real stacks' pixels more
    than 10 levels out of the frames' colour range). A true all-in-focus pixel is one of
    the frames', colour included. The frames are decoded up to white, so their colours
    are the displayed ones, clipped frames included: what the result shows is judged
    against what they show, wherever they clipped (stop 34 left the colour open there,
    and two thirds of pcb10's remaining fringes were those pixels). At a kept sum the
    ratios are two bands in the differences, and the differences a box: each is kept in
    turn, for ``COLOUR_ROUNDS`` rounds.
    """
    capped = cv2.min(out, _WHITE)
    moved = cv2.inRange(colour_codes(capped), low_codes, high_codes) == 0
    if not moved.any():
        return
    # the whole strip at once with OpenCV, then copied back where a pixel moved (a third of
    # pcb10's pixels, most by a little; indexing them one by one was slower at stop 34)
    rebuilt = _kept_colour(capped, low_codes, high_codes)
    rebuilt = cv2.min(cv2.max(rebuilt, low), high)
    beyond = (rebuilt >= 1.0).view(np.uint8)  # displayed at white: the value beyond stays
    cv2.copyTo(cv2.max(rebuilt, out), beyond, rebuilt)
    cv2.copyTo(rebuilt, moved.astype(np.uint8), out)


def _kept_colour(pixels, low_codes, high_codes):
    """RGB ``pixels`` at their sum ``S = R + G + B``, with their chromaticity and colour
    differences kept to ``[low_codes, high_codes]`` (the four codes of
    :func:`colour_codes`).

    At a kept sum a pixel is its ``(R, B)`` (``G = S - R - B``): the ratios bound them to
    ``[r_low T - f, r_high T - f]`` (``f`` the floor, ``T = S + 3 f``), a box, and the
    differences are ``R - G = 2 R + B - S``, ``B - G = R + 2 B - S``, whose box maps back
    by ``R = (S + 2 (R - G) - (B - G)) / 3``, ``B = (S - (R - G) + 2 (B - G)) / 3``. Each
    box is kept in turn, for ``COLOUR_ROUNDS`` rounds. One channel at a time, as
    :func:`colour_codes` (pcb10's strips: 0.05 s, against 0.11 s in channel pairs)."""
    floor, top = float(CHROMA_FLOOR), float(CODE_MAX)
    red, green, blue = cv2.split(pixels)
    total = cv2.add(cv2.add(red, green), blue)
    floored = cv2.add(total, 3.0 * floor)
    third = cv2.multiply(total, 1.0 / 3.0)

    def share_bound(codes):  # code / top * T - f
        return cv2.subtract(cv2.multiply(codes, floored, scale=1.0 / top, dtype=cv2.CV_32F),
                            floor)

    def difference_bound(codes):  # 2 code / top - 1
        return cv2.subtract(cv2.multiply(codes, 2.0 / top, dtype=cv2.CV_32F), 1.0)

    low, high = cv2.split(low_codes), cv2.split(high_codes)
    red_low, blue_low, red_high, blue_high = (share_bound(c) for c in (*low[:2], *high[:2]))
    rg_low, bg_low, rg_high, bg_high = (difference_bound(c) for c in (*low[2:], *high[2:]))
    for _ in range(COLOUR_ROUNDS):
        red = cv2.min(cv2.max(red, red_low), red_high)
        blue = cv2.min(cv2.max(blue, blue_low), blue_high)
        red_green = cv2.subtract(cv2.addWeighted(red, 2.0, blue, 1.0, 0.0), total)
        blue_green = cv2.subtract(cv2.addWeighted(red, 1.0, blue, 2.0, 0.0), total)
        red_green = cv2.min(cv2.max(red_green, rg_low), rg_high)
        blue_green = cv2.min(cv2.max(blue_green, bg_low), bg_high)
        red = cv2.add(cv2.addWeighted(red_green, 2.0 / 3.0, blue_green, -1.0 / 3.0, 0.0), third)
        blue = cv2.add(cv2.addWeighted(red_green, -1.0 / 3.0, blue_green, 2.0 / 3.0, 0.0), third)
    return cv2.merge([red, cv2.subtract(cv2.subtract(total, red), blue), blue])


# Flat areas: where the frames' per-pixel max and min images both hold less fine detail
# (band g - G_1px g, std over 7 px, display levels of 8 bits) than FLAT_DETAIL[0], every
# frame is flat there; above FLAT_DETAIL[1] the result is left alone.
FLAT_DETAIL = (0.8 / 255.0, 1.5 / 255.0)
FLAT_BAND_PX = (1.0, 7.0)  # (sigma, window) of the fine band judged
FLAT_NOISE_BAND_PX = 2.0  # the result's band g - G_2px g is replaced there
FLAT_BLEND_PX = 2.0  # smoothing of the flat map


def quiet_flat_areas(
    image: np.ndarray, average: np.ndarray, support: FrameSupport
) -> tuple[np.ndarray, float]:
    """Where every frame is flat, the restored fine band is noise: take the average's.

    Deconvolution amplifies the average's noise (a white-noise gain of 3-30 on the
    IPSFs of real stacks) and where no frame shows fine detail there is none to
    restore. A pixel is flat where the fine detail of both the frames' per-pixel
    maximum and minimum images (each frame's texture shows in one or the other) is
    below ``FLAT_DETAIL`` (8-bit display levels, like :func:`prefer_sharpest`'s floor:
    JPEG frames' own grain is 0.3-0.6 levels, a 0.01 linear noise 1-3). There the
    band ``g - G_2px g`` of ``image`` is replaced by the average's, so the low
    frequencies the deconvolution restored (haze, Sec. 4.1's ends) stay. Issue 13:
    on the four real stacks flat-area noise went from 0 to 34 of 34 regions as good
    as focus-stack's, with no region losing sharpness or haze; on the synthetic scenes
    -0.1 to +0.3 dB. Blocks where a frame reaches white (the codes' end) are never judged
    flat: beyond it the frames' range knows nothing (blown highlights, float frames in
    other units). In place; returns the image and the fraction of pixels replaced over
    half.
    """
    sigma_px, window_px = FLAT_BAND_PX
    detail = None
    for codes in (support.high, support.low):
        grey = _display(from_codes(_grey(codes.reshape(image.shape))))
        energy = _detail_energy(grey, sigma_px, window_px)
        detail = energy if detail is None else np.maximum(detail, energy)
    low, high = FLAT_DETAIL
    alpha = np.clip((np.float32(high) - detail) / np.float32(high - low), 0.0, 1.0)
    # at or beyond white in some frame the codes end, and with them what the range knows
    # (blown highlights; float frames in other units): not judged flat there
    beyond = _at_white(support.high.reshape(image.shape))
    alpha[_reduced(beyond.astype(np.float32), ENERGY_BLOCK_PX) > 0] = 0.0
    alpha = cv2.GaussianBlur(alpha, (0, 0), FLAT_BLEND_PX / ENERGY_BLOCK_PX)
    alpha = cv2.resize(alpha, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_LINEAR)
    reach = int(np.ceil(4 * FLAT_NOISE_BAND_PX))  # rows the band's Gaussian reads around a strip
    rows = image.shape[0]
    above = None  # the rows above the strip as they were before the last strip changed them
    for r0 in range(0, rows, CLIP_STRIP_ROWS):  # by strips: a strip's worth of temporaries
        r1 = min(rows, r0 + CLIP_STRIP_ROWS)
        if not np.any(alpha[r0:r1] > 1e-3):
            above = None
            continue  # nothing flat here (most strips of a textured scene)
        a0, a1 = max(0, r0 - reach), min(rows, r1 + reach)
        before = image[a0:a1] if above is None else np.concatenate((above, image[r0:a1]))
        noise = average[a0:a1] - before  # the average's fine band minus the result's
        noise -= cv2.GaussianBlur(noise, (0, 0), FLAT_NOISE_BAND_PX, borderType=cv2.BORDER_REFLECT)
        above = image[max(0, r1 - reach) : r1].copy()
        band = noise[r0 - a0 : r1 - a0]
        image[r0:r1] += scale_channels(band, alpha[r0:r1])  # no strip-size temporary
    return image, float(np.mean(alpha > 0.5))


def _at_white(codes: np.ndarray) -> np.ndarray:
    """Pixels at the end code (white or beyond) in any channel (the channels' maximum by
    OpenCV: np.any over the channel axis took 43 ms on 3 Mpx)."""
    channels = _channels(codes)
    top = channels[0]
    for channel in channels[1:]:
        top = cv2.max(top, channel)
    return top == CODE_MAX


def keep_to_frames(image: np.ndarray, support: FrameSupport, clipped=None):
    """:func:`clip_to_frames`, then :func:`prefer_sharpest` (a blend of two images within
    the range stays within it). Returns the image (in place) and the blended fraction."""
    return prefer_sharpest(clip_to_frames(image, support, clipped), support, clipped)


def _display(grey: np.ndarray) -> np.ndarray:
    """A linear grey image in display terms (gamma 1/2.2), where the contrast floor is set."""
    return cv2.pow(np.maximum(grey, 0.0), 1 / 2.2)


def _detail_energy(grey: np.ndarray, sigma_px: float, window_px: float) -> np.ndarray:
    """Local std (Gaussian window ``window_px``) of the band ``g - G_sigma * g``, per
    ``ENERGY_BLOCK_PX`` block (the band is taken at full resolution, or at half for a
    sigma of 2 px and more, where it holds nothing finer)."""
    step = 2 if sigma_px >= 2 else 1
    if step > 1:
        grey = _reduced(grey, step)
    detail = grey - cv2.GaussianBlur(grey, (0, 0), sigma_px / step)
    energy = _reduced(detail * detail, ENERGY_BLOCK_PX // step)
    energy = cv2.GaussianBlur(energy, (0, 0), window_px / ENERGY_BLOCK_PX)
    return np.sqrt(np.maximum(energy, 0.0))


def prefer_sharpest(
    image: np.ndarray, support: FrameSupport, clipped=None
) -> tuple[np.ndarray, float]:
    """Blend towards the sharpest frame where it shows more local detail than ``image``.

    Per detail band (``DETAIL_BANDS``: fine ``g - G_1px * g`` in 7 px windows, coarse
    ``g - G_4px * g`` in 15 px windows) the weight is ``clip(gap / floor - 1, 0, 1)``,
    ``gap`` the frame's local std minus the image's on the display-gamma grey image and
    ``floor`` = 2 levels of 8 bits; the larger of the bands' weights is smoothed over
    6 px. Only detail above the floor counts, so noise in flat areas never swaps; where
    deconvolution restored the detail its result stays. The coarse band catches what
    the fine one misses: low-frequency contrast lost to the IPSF's tail (haze), and the
    ends of the stack's focus range (Sec. 4.1), where the end frames are the sharpest.
    The weights are computed per 4 px block (they vary over 6 px and more) and
    interpolated. Pixels ``clipped`` in some frame keep ``image`` (the frames' codes
    end at white). Returns the blended image (in place) and the fraction of pixels
    blended over half.
    """
    sharpest = support.sharpest.reshape(image.shape)
    frame_grey = _display(from_codes(_grey(sharpest)))
    image_grey = _display(_grey(image))
    alpha = None
    for sigma_px, window_px in DETAIL_BANDS:
        gap = _detail_energy(frame_grey, sigma_px, window_px)
        gap -= _detail_energy(image_grey, sigma_px, window_px)
        band = np.clip(gap / np.float32(CONTRAST_FLOOR) - 1.0, 0.0, 1.0)
        alpha = band if alpha is None else np.maximum(alpha, band)
    alpha = cv2.GaussianBlur(alpha, (0, 0), BLEND_SIGMA_PX / ENERGY_BLOCK_PX)
    size = (image.shape[1], image.shape[0])
    alpha = cv2.resize(alpha, size, interpolation=cv2.INTER_LINEAR)
    saturated = _at_white(sharpest)  # the sharpest frame's codes end there
    if np.any(saturated):
        alpha[saturated] = 0.0
    fraction = float(np.mean(alpha > 0.5))
    for out, codes in zip(_channels(image), _channels(sharpest)):
        frame = from_codes(codes)
        frame -= out
        frame *= alpha
        out += frame
    return image, fraction
