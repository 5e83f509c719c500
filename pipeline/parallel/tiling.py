"""Tiled deconvolution with dask (the edge around :mod:`pipeline.core.deconvolve`).

The whole-image quantities (noise level, regularisation, RL background) are
resolved once by :func:`pipeline.core.deconvolve.dispatch.plan`; every tile is then restored with
that plan by ``dask.array.map_overlap``. Overlap depth is ``plan.depth``, derived
from the restoration operator's support (see :func:`pipeline.core.deconvolve.common.filter_depth`):

* Wiener: the radius beyond which the impulse response of
  ``K* / (|K|^2 + lam |D|^2)`` holds less than 1e-5 of its absolute mass, so data
  beyond the overlap (and the tile's own reflection/taper padding) change a kept
  pixel by less than ~1e-5 of the data range. For a pillbox with spectral zeros and
  little noise that radius can exceed the frame (the filter is not local): then
  the tiles are the whole frame.
* Richardson-Lucy: one iteration reads the data a kernel radius away and spreads
  back another, so ``n`` iterations reach ``2 n r`` in the worst case; the actual
  reach is that of the linearised iteration (Landweber), whose support grows like
  ``r sqrt(n)`` (powers of ``K^T K`` spread like a random walk). Its 1e-5 radius plus
  one kernel radius (the extended domain's margin) is used.
* Sparse (ADMM): not tiled (one tile, whatever ``tile_px``): the hyper-Laplacian
  shrinkage is non-linear and tiles differed from the whole frame by 0.04-0.08 at
  every overlap tried (40-120 px), so the quality option costs whole-frame memory.
  ``overlap_px`` still forces tiles (for the accuracy benchmark).

Frames up to ``WHOLE_FRAME_PX`` (numpy input, no forced ``overlap_px``) are restored
whole, without dask: one FFT grid per channel costs less than tiles that each carry
their overlap and padding. The colour channels are restored side by side, one per core,
each with single-threaded FFTs (a grey frame's FFTs use every core instead,
``scipy.fft.set_workers``).
Larger frames are tiled with tiles at least ``TILE_OVER_REACH`` times the overlap (a
tile that is mostly overlap repeats its neighbours' work); tiles of one size share
their kernel spectra (cached in the plan) and run single-threaded FFTs in the dask
threads (one level of parallelism).

Frame edges use ``boundary="none"``: an edge tile keeps the frame edge and treats
it exactly as :func:`pipeline.core.deconvolve.dispatch.deconvolve` does (same padding or the
same extended domain), so the tiled result equals the untiled one.
"""

from __future__ import annotations

import logging
import os
from functools import partial

import numpy as np
from scipy import fft as sfft

from pipeline.core import deconvolve as dc
from pipeline.core.deconvolve.common import channel_threads
from pipeline.core.deconvolve.wiener import TAPER_PX
from pipeline.errors import InputError

log = logging.getLogger(__name__)

MIN_TILE_PX = 64  # smaller tiles are all overlap: the same result, many times the work
WHOLE_FRAME_PX = 16_000_000  # frames up to this are restored whole (~70 B/px at the peak)
# frames up to this give every colour channel its own thread even where there are fewer
# cores: pcb7 (3 Mpx) gains 0.02 s for +36 MiB; at 12 Mpx the third channel's grids cost
# +200 MiB (0.62 -> 0.74 of focus-stack's peak) for no measurable time
CHANNEL_PER_THREAD_PX = 4_000_000
TILE_OVER_REACH = 4  # a tile is at least this many times its overlap (reach + padding)


def _is_dask(image) -> bool:
    """A dask array, without importing dask.array for numpy input."""
    return type(image).__module__.split(".")[0] == "dask" and hasattr(image, "chunks")


def deconvolve_tiled(
    image,
    kernel,
    *,
    method: str = "wiener",
    tile_px: int = 1024,
    overlap_px: int | None = None,
    saturation=None,
    censored=None,
    on_plan=None,
    **options,
):
    """:func:`pipeline.core.deconvolve.dispatch.deconvolve` over overlapping tiles with dask.

    Parameters
    ----------
    image : numpy or dask array, (rows, cols) or (rows, cols, channels)
        A numpy image is split into ``tile_px`` chunks; a dask image keeps its
        chunks (uneven chunks are fine). The plan needs whole-image statistics, so a
        dask image is computed once for them (persist it first if that is costly).
    kernel : array
        PSF/IPSF (odd sides, centred, non-negative, sums to 1).
    method, saturation, censored, **options
        As :func:`pipeline.core.deconvolve.deconvolve` (``censored`` is tiled with the image).
    tile_px : int
        Tile side for numpy frames larger than ``WHOLE_FRAME_PX`` (smaller ones are
        restored whole) or with ``overlap_px`` given; raised to ``TILE_OVER_REACH`` times
        the overlap plus padding. The work per tile is ``(tile_px + 2 depth)^2``.
    overlap_px : int, optional
        Overlap ``depth``; default the operator's support (``plan.depth``, see the
        module notes). Smaller values trade accuracy at tile seams for time.
    on_plan : callable, optional
        Called with the whole-image :class:`~pipeline.core.deconvolve.common.Plan` once it
        is made (what the automatic parameters came to, for a sidecar).

    Returns
    -------
    numpy or dask array
        Same kind, shape and dtype policy as the input (dask stays lazy).
    """
    tile_px = int(tile_px)
    if tile_px < 1:
        raise InputError(f"tile_px must be >= 1, got {tile_px!r}")
    if overlap_px is not None and (isinstance(overlap_px, bool) or int(overlap_px) < 0):
        raise InputError(f"overlap_px must be an integer >= 0 or None, got {overlap_px!r}")
    if tile_px < MIN_TILE_PX:  # each tile costs (tile + 2 depth)^2: tiny tiles only add work
        log.info("tile_px %d raised to %d px", tile_px, MIN_TILE_PX)
        tile_px = MIN_TILE_PX
    lazy = _is_dask(image)
    whole = np.asarray(image.compute() if lazy else image)
    cores = os.cpu_count() or 1
    if not lazy and overlap_px is None and whole.shape[0] * whole.shape[1] <= WHOLE_FRAME_PX:
        # one level of parallelism: the colour channels side by side (each with
        # single-threaded FFTs), or, for one channel, the FFTs' threads. With two cores or
        # more, frames up to CHANNEL_PER_THREAD_PX give every channel its own thread: three
        # as 2 + 1 rounds on two cores left one idle a third of the time (pcb7's
        # deconvolution 0.37 -> 0.35 s, same bits)
        channels = whole.shape[2] if whole.ndim == 3 else 1
        small = whole.shape[0] * whole.shape[1] <= CHANNEL_PER_THREAD_PX
        threads = max(cores, channels) if cores > 1 and small else cores
        with sfft.set_workers(cores), channel_threads(threads):
            p = dc.plan(
                whole, kernel, method=method, saturation=saturation, censored=censored, **options
            )
            if on_plan is not None:
                on_plan(p)
            return dc.restore(whole, p, censored)
    import dask.array as da  # only the tiled path needs it

    with sfft.set_workers(cores):
        p = dc.plan(
            whole, kernel, method=method, saturation=saturation, censored=censored, **options
        )
    if on_plan is not None:
        on_plan(p)
    dtype = np.float32 if whole.dtype == np.float32 else np.float64
    if not lazy and overlap_px is None:  # else most of each tile's work is overlap
        tile_px = max(tile_px, TILE_OVER_REACH * (2 * p.depth + TAPER_PX))
    arr = (
        image
        if lazy
        else da.from_array(whole, chunks=(tile_px, tile_px, *whole.shape[2:]), name=False)
    )
    arr = arr.astype(dtype)
    if arr.ndim == 3:
        arr = arr.rechunk({2: -1})
    depth = {2: 0} if arr.ndim == 3 else {}
    reach = p.depth if overlap_px is None else int(overlap_px)
    for axis in (0, 1):
        if reach >= arr.shape[axis]:  # the operator reaches across the frame: one tile
            arr = arr.rechunk({axis: -1})
            depth[axis] = 0
        else:
            depth[axis] = reach
    meta = np.empty((0,) * arr.ndim, dtype=dtype)
    if censored is None:
        out = da.map_overlap(
            partial(dc.restore, p=p),
            arr,
            depth=depth,
            boundary="none",
            trim=True,
            dtype=dtype,
            meta=meta,
        )
    else:
        mask = np.asarray(censored, dtype=bool)
        mask = mask[..., np.newaxis] if arr.ndim == 3 else mask
        mask_arr = da.from_array(
            mask, chunks=arr.chunks[:2] + ((1,) if arr.ndim == 3 else ()), name=False
        )
        out = da.map_overlap(
            _restore_censored,
            arr,
            mask_arr,
            p=p,
            depth=depth,
            boundary="none",
            trim=True,
            dtype=dtype,
            meta=meta,
            align_arrays=False,
        )
    return out if lazy else out.compute()


def _restore_censored(y, mask, p):
    return dc.restore(y, p, mask[..., 0] if mask.ndim == 3 else mask)
