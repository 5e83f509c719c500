"""How far a depth-aware linear restoration can go on the shipped motorcycle stack, given
the true depth (issue 13's +1 dB for the quality method, which ``--method multiframe``
misses there: +0.58 dB in ``results/real_regions/synthetic_guard.md``).

    python tests/benchmarks/multiframe_depth_bound.py [--out results/quality_method/depth_bound.md]

The motorcycle is rendered by ``pipeline.core.simulate`` with occlusion ("over"
compositing of depth layers, sub-aperture cells at occluding edges); 39% of its pixels lie
within 8 px of a depth discontinuity (``synthetic_guard.motorcycle_regions``), and the
multi-frame method keeps the default's result there. Each row restores the same aligned
frames (the job's Lanczos warp, captured from ``pipeline.jobs.multiframe``) with the same
per-frame kernels (Eqs. 2-4), the same candidate depths and the same natural-image prior:

* ``default``: the main job (Sec. 9 average, one kernel);
* ``multiframe``: ``--method multiframe`` as shipped (depth chosen by the frames' residual,
  :func:`pipeline.core.multiframe.depth_index`; blended to the default near depth changes);
* ``per-depth, true depth (gated / ungated)``: the same, each pixel taking the estimate of
  the candidate nearest its true depth (the stack's thin lens, ``v = 1/(1/f - 1/u)``), with
  the method's blend to the default near depth changes, and without it;
* ``scatter model, true / estimated depth``: one image solved from all frames at once under
  a spatially varying blur, ``y_k = sum_d K_kd * (m_d x)``, ``m_d`` the hat weights of each
  pixel's depth between its two nearest candidates (the renderer's own split without
  occlusion), by conjugate gradients on the normal equations with the prior
  ``lam |Laplacian x|^2`` (:data:`CG_ITERATIONS`; the result moves by under 0.01 dB from 20
  to 60). With a constant depth it equals the per-depth Wiener estimate (rms 1e-4).

No row models occlusion. A restoration that does not is bounded by these rows near the
edges, whatever its depth map; that is what the table measures.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy import fft as sfft

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS / "benchmarks"))

from synthetic_guard import motorcycle_regions, print_and_save, run_job, scores  # noqa: E402

from pipeline.core import multiframe  # noqa: E402
from pipeline.core.deconvolve.common import _kernel_fft, _laplacian_spectrum  # noqa: E402
from pipeline.core.quality import psnr  # noqa: E402
from pipeline.io.profiles import load_lens  # noqa: E402
from pipeline.io.read import read_frame  # noqa: E402
from pipeline.jobs import multiframe as multiframe_job  # noqa: E402
from pipeline.parallel.scheduler import scheduler_context  # noqa: E402

SAMPLE = TESTS.parent / "stacks" / "motorcycle"
CG_ITERATIONS = 30


def true_positions(depth_mm: np.ndarray, focal_length_mm: float) -> np.ndarray:
    """Each pixel's in-focus image distance (thin lens), the frames' focus coordinate."""
    return 1.0 / (1.0 / focal_length_mm - 1.0 / depth_mm)


def hat_weights(position: np.ndarray, depths: np.ndarray) -> np.ndarray:
    """(rows, cols, n_depths) weights of each pixel's two nearest candidates, linear in
    the focus coordinate and clamped at the ends."""
    j = np.clip(np.searchsorted(depths, position) - 1, 0, len(depths) - 2)
    t = np.clip((position - depths[j]) / (depths[j + 1] - depths[j]), 0.0, 1.0)
    weights = np.zeros((*position.shape, len(depths)))
    np.put_along_axis(weights, j[..., None], (1.0 - t)[..., None], -1)
    np.put_along_axis(weights, (j + 1)[..., None], t[..., None], -1)
    return weights


def scatter_solve(frames, kernels, weights, fallback, iterations=CG_ITERATIONS):
    """Conjugate gradients for ``min sum_k |sum_d K_kd * (m_d x) - y_k|^2 + lam |L x|^2``
    per channel, on frames reflected by the largest kernel's half width (data counted
    inside the frame only), started from ``fallback``."""
    n, rows, cols, channels = frames.shape
    pad = max(k.shape[0] for ks in kernels for k in ks) // 2 + 1
    shape = (rows + 2 * pad, cols + 2 * pad)
    masks = np.pad(weights, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    used = [d for d in range(masks.shape[2]) if masks[..., d].any()]
    spectra = {d: [_kernel_fft(k, shape, np.float64) for k in kernels[d]] for d in used}
    d2 = _laplacian_spectrum(shape, np.float64)
    inside = np.zeros(shape)
    inside[pad:-pad, pad:-pad] = 1.0
    out = np.empty((rows, cols, channels), np.float32)

    def forward(x):
        z = [0.0] * n
        for d in used:
            xf = sfft.rfft2(masks[..., d] * x)
            z = [zk + kf * xf for zk, kf in zip(z, spectra[d])]
        return [sfft.irfft2(zk, s=shape) for zk in z]

    def adjoint(residuals):
        rf = [sfft.rfft2(inside * r) for r in residuals]
        total = np.zeros(shape)
        for d in used:
            g = sum(np.conj(kf) * r for kf, r in zip(spectra[d], rf))
            total += masks[..., d] * sfft.irfft2(g, s=shape)
        return total

    for c in range(channels):
        lam = multiframe.regularisation(frames[..., c], fallback[..., c])
        y = [np.pad(frames[k, ..., c], pad, mode="reflect") for k in range(n)]

        def normal(x, lam=lam):
            return adjoint(forward(x)) + lam * sfft.irfft2(d2 * sfft.rfft2(x), s=shape)

        x = np.pad(fallback[..., c].astype(np.float64), pad, mode="reflect")
        r = adjoint(y) - normal(x)
        p, rr = r.copy(), float(np.sum(r * r))
        for _ in range(iterations):
            ap = normal(p)
            a = rr / float(np.sum(p * ap))
            x += a * p
            r -= a * ap
            rr_new = float(np.sum(r * r))
            p, rr = r + (rr_new / rr) * p, rr_new
        out[..., c] = x[pad:-pad, pad:-pad]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    logging.disable(logging.WARNING)
    truth = read_frame(SAMPLE / "ground_truth.tif")
    regions = motorcycle_regions(SAMPLE, truth)
    lens = load_lens(SAMPLE / "lens.toml")
    position = true_positions(np.load(SAMPLE / "depth_mm.npy"), lens.focal_length_mm)
    captured, oracle = {}, {}
    restore, depth_index, steady = (multiframe.restore, multiframe.depth_index,
                                    multiframe.steady_weight)

    def capturing_restore(frames, kernels_at, depths, fallback, **kw):
        captured.update(frames=frames, kernels_at=kernels_at, depths=depths, fallback=fallback)
        return restore(frames, kernels_at, depths, fallback, **kw)

    def depth_index_given(frames, kernels_at, depths, lam, **kw):
        index, unexplained = depth_index(frames, kernels_at, depths, lam, **kw)
        if oracle.get("depth") and index.shape == position.shape:
            index = np.abs(position[..., None] - depths).argmin(-1).astype(np.int32)
        return index, unexplained

    def steady_given(index, radius_px, blocked):
        weight = steady(index, radius_px, blocked)
        return np.ones_like(weight) if oracle.get("ungated") else weight

    rows = {}
    multiframe_job.multiframe.restore = capturing_restore
    multiframe.depth_index, multiframe.steady_weight = depth_index_given, steady_given
    try:
        with scheduler_context(threads=2), tempfile.TemporaryDirectory() as tmp:
            rows["default"] = run_job(SAMPLE, Path(tmp) / "d.tif")[0]
            rows["multiframe"] = run_job(SAMPLE, Path(tmp) / "m.tif", method="multiframe")[0]
            for label, flags in (("gated", {"depth": True}),
                                 ("ungated", {"depth": True, "ungated": True})):
                oracle.update(flags)
                rows[f"per-depth, true depth ({label})"] = run_job(
                    SAMPLE, Path(tmp) / "o.tif", method="multiframe")[0]
                oracle.clear()
    finally:
        multiframe_job.multiframe.restore = restore
        multiframe.depth_index, multiframe.steady_weight = depth_index, steady
    frames, depths, fallback = (captured[k] for k in ("frames", "depths", "fallback"))
    kernels = [captured["kernels_at"](float(d), 1.0) for d in depths]
    grey = frames.mean(axis=3)
    lam = multiframe.regularisation(grey, fallback.mean(axis=2))
    estimated, _ = depth_index(grey, lambda d, s: kernels[list(depths).index(d)], depths, lam)
    rows["scatter model, true depth"] = scatter_solve(
        frames, kernels, hat_weights(position, depths), fallback)
    rows["scatter model, estimated depth"] = scatter_solve(
        frames, kernels, np.eye(len(depths))[estimated], fallback)
    base = psnr(rows["default"], truth)
    lines = ["| restoration | PSNR dB / SSIM | PSNR near edge | PSNR away | gain over default dB |",
             "|---|---|---|---|---|"]
    for label, image in rows.items():
        cells = scores(image, truth, regions)
        lines.append(f"| {label} | " + " | ".join(cells)
                     + f" | {psnr(image, truth) - base:+.2f} |")
    print_and_save(lines, args.out)


if __name__ == "__main__":
    main()
