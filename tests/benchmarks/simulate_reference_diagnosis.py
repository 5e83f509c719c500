"""Diagnosis runs behind tests/benchmarks/results/simulate_reference/diagnosis.md (issue 14).

Run: ``.venv/bin/python tests/benchmarks/simulate_reference_diagnosis.py`` (about 2 min).
Prints: (1) the box-layer seam term (constant-radiance scene vs the ESF formula), (2) hat
(linear-in-D) layers at the plan's own representatives vs today's box layers, (3) the
per-step layer estimates for sweeps (whole-exposure, triangle bound, shift-coupled),
(4) the over model's error profile at an edge with both sides out of focus.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
from scipy import signal

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from reference import cases as rc  # noqa: E402
from reference import smooth  # noqa: E402
from reference.disk import pixel_disk_kernels  # noqa: E402
from reference.optics import grid_radius  # noqa: E402

from pipeline.core import psf, simulate  # noqa: E402
from pipeline.core.scene import Scene  # noqa: E402

CS = rc.build_cases()


def seams() -> None:
    print("== (1) box-layer seams: ramp static narrow")
    c = CS["ramp static narrow"]
    depth = c.scene.surfaces[0].depth_mm
    tex = c.scene.surfaces[0].radiance[:, :, 0]
    lens, p = c.camera.lens, c.camera.motion.start_mm
    mu, sigma = tex.mean(), tex.std()
    for tol in (1e-2, 1e-3):
        pl = simulate.plan(c.scene, c.camera, tolerance=tol)
        layers = pl.bands[0].layers
        ends = np.array([layer.inv_hi for layer in layers])
        idx = np.searchsorted(ends, 1 / depth[:, 0], side="left")
        err2 = 0.0
        for r in range(depth.shape[0] - 1):
            a, b = idx[r], idx[r + 1]
            if a == b:
                continue
            ka = psf.integrated_psf(lens, layers[a].depth_mm, c.camera.motion)
            kb = psf.integrated_psf(lens, layers[b].depth_mm, c.camera.motion)
            h = max(ka.shape[0], kb.shape[0]) // 2
            la = np.pad(ka.sum(axis=1), h - ka.shape[0] // 2)
            lb = np.pad(kb.sum(axis=1), h - kb.shape[0] // 2)
            err2 += depth.shape[1] * np.sum(np.cumsum(la - lb) ** 2)
        pred = mu / sigma * np.sqrt(err2 / depth.size)
        results = {}
        for label, rad in (("texture", tex), ("constant", np.full_like(tex, mu)),
                           ("zero-mean texture", tex - mu)):
            sc = Scene.from_depth(rad, depth)
            out = simulate.render(sc, c.camera, plan_=simulate.plan(sc, c.camera, tolerance=tol))
            ref = smooth.render_smooth(rad, depth, f_mm=12.5, f_number=1.4, pitch_mm=0.02,
                                       times_s=[0, 0.1], positions_mm=[p, p], p_ref_mm=p,
                                       n_time=1)
            results[label] = float(np.sqrt(np.mean((out - ref) ** 2)) / sigma)
        print(f"tol {tol:g}: {len(layers)} layers, est {pl.estimated_error:.3g}; measured "
              + ", ".join(f"{k} {v:.3g}" for k, v in results.items())
              + f"; ESF seam formula {pred:.3g}")


def hats() -> None:
    print("== (2) hat layers at the plan's representatives: ramp static narrow")
    c = CS["ramp static narrow"]
    depth = c.scene.surfaces[0].depth_mm
    tex = c.scene.surfaces[0].radiance[:, :, 0]
    p = c.camera.motion.start_mm
    ref = c.reference()
    for tol in (1e-2, 1e-3):
        pl = simulate.plan(c.scene, c.camera, tolerance=tol)
        reps = np.array(sorted(layer.inv_rep for layer in pl.bands[0].layers))
        pos = np.interp(1 / depth, reps, np.arange(reps.size))
        i0 = np.clip(np.floor(pos).astype(int), 0, max(reps.size - 2, 0))
        th = pos - i0
        pad, out = 8, np.zeros_like(tex)
        for j in range(reps.size):
            w = np.where(i0 == j, 1 - th, 0) + np.where(i0 + 1 == j, th, 0)
            if not w.any():
                continue
            k = pixel_disk_kernels([grid_radius(12.5, 1.4, 0.02, p, reps[j], p)], pad)[0]
            img = np.pad(tex * w, pad, mode="reflect")
            out += signal.fftconvolve(img, k, mode="same")[pad:-pad, pad:-pad]
        box = simulate.render(c.scene, c.camera, plan_=pl)
        print(f"tol {tol:g}: {reps.size} layers: box {rc.rel_rms(box, ref, c.contrast):.3g}, "
              f"hat {rc.rel_rms(out, ref, c.contrast):.3g}, est {pl.estimated_error:.3g}")


def per_step() -> None:
    print("== (3) layer estimates with magnification sub-steps (occlusion off)")
    for name in ("ramp sweep", "wide-angle"):
        c = CS[name]
        rows, cols = c.scene.shape
        radii = {"corner": np.array([(cols - 1) / 2, (rows - 1) / 2]),
                 "rms radius": np.array([cols / math.sqrt(12), rows / math.sqrt(12)])}
        for tol in (1e-2, 1e-3):
            pl = simulate.plan(c.scene, c.camera, tolerance=tol, occlusion=False)
            band, lens = pl.bands[0], c.camera.lens
            present = np.unique(1 / c.scene.surfaces[0].depth_mm)
            ends = np.array([layer.inv_hi for layer in band.layers])
            idx = np.searchsorted(ends, present, side="left").clip(0, len(band.layers) - 1)
            size = max(psf.integrated_psf(lens, simulate._depth(d), s.profile).shape[0]
                       for d in (present[0], present[-1]) for s in band.steps)
            sp = simulate._Spectra(simulate._grid(size))

            def spec(d, prof, sp=sp, lens=lens):
                return sp.of(psf.integrated_psf(lens, simulate._depth(d), prof))

            whole = tri = 0.0
            coupled = dict.fromkeys(radii, 0.0)
            for d, i in zip(present, idx):
                r = band.layers[i].inv_rep
                whole = max(whole, sp.error(spec(d, band.profile) - spec(r, band.profile)))
                diffs = [(s, spec(d, s.profile) - spec(r, s.profile)) for s in band.steps]
                tri = max(tri, sum(s.weight * sp.error(k) for s, k in diffs))
                for label, vec in radii.items():
                    tot = sum(s.weight * k * sp.shift(*(vec * (s.scale - 1))) for s, k in diffs)
                    coupled[label] = max(coupled[label], sp.error(tot))
            print(f"{name} tol {tol:g}: {len(band.layers)} layers, {len(band.steps)} steps; "
                  f"whole-exposure {whole:.3g}, triangle {tri:.3g}, coupled rms radius "
                  f"{coupled['rms radius']:.3g} / corner {coupled['corner']:.3g}")


def edge_profile() -> None:
    print("== (4) over model at an edge with both sides out of focus (2 exact layers)")
    c = CS["edge focus between"]
    p = c.camera.motion.start_mm
    pl = simulate.plan(c.scene, c.camera, tolerance=1e-3)
    far, near = 1 / rc.FAR_MM, 1 / rc.NEAR_MM
    layers = (simulate.Layer(-np.inf, far, far), simulate.Layer(far, near, near))
    pl2 = dataclasses.replace(
        pl, bands=tuple(dataclasses.replace(b, layers=layers) for b in pl.bands), occlusion=True
    )
    out, ref = simulate.render(c.scene, c.camera, plan_=pl2), c.reference()
    col = np.sqrt(np.mean((out - ref) ** 2, axis=0)) / c.contrast
    rn = grid_radius(12.5, 1.4, 0.02, p, near, p)
    rf = grid_radius(12.5, 1.4, 0.02, p, far, p)
    band = np.abs(np.arange(rc.COLS) - (rc.EDGE_COL - 0.5)) <= abs(rn) + 0.5
    total = rc.rel_rms(out, ref, c.contrast)
    print(f"rho_near {rn:.2f} px, rho_far {rf:.2f} px; total {total:.3g};"
          f" per-column error cols 28-36 {np.round(col[28:37], 3).tolist()}; band cols "
          f"{np.flatnonzero(band).tolist()}: RMS {np.sqrt(np.mean(col[band] ** 2)):.3g}, "
          f"outside {np.sqrt(np.mean(col[~band] ** 2)):.2g}")


if __name__ == "__main__":
    seams()
    hats()
    per_step()
    edge_profile()
