"""Generate the sample focal stack ``stacks/motorcycle/`` (deterministic).

Run from the repository root::

    python stacks/generate_motorcycle.py

Scene: scikit-image's copy of the Middlebury 2014 "Motorcycle" pair (bundled,
``skimage.data.stereo_motorcycle()``): the left image and its ground-truth disparity
(``inf`` where unknown). The skimage copy is the benchmark downsampled 4x; its calibration,
as the skimage docstring gives it, is the full-resolution calibration divided by 4:
``f = 3979.911 / 4 = 994.978 px``, ``doffs = 124.343 / 4 = 31.086 px``, baseline
``B = 193.001 mm`` (unchanged). Depth (mm) is ``Z = B f / (d + doffs)`` with the disparity
``d`` in the same (quarter-scale) pixels.

Steps:

1. crop to 740 x 500 and downscale 2x (block mean) to 370 x 250: radiance is averaged
   after sRGB linearisation (exact sRGB EOTF, :func:`pipeline.core.colour.srgb_to_linear`); depth
   is averaged as inverse depth over the valid pixels of each block (NaN if none);
2. map the real depth range monotonically onto 450-2000 mm, linearly in inverse depth
   (disparity is linear in inverse depth, so this is the scene seen by a closer camera with
   a rescaled baseline); unknown depth is filled with the nearest valid depth;
3. the lens is ``fujinon-12.5mm-f1.4-sony-1-3in`` with its 1024 x 768 x 4.65 um sensor
   resampled so that the 370 px frame spans the sensor's width: pixel pitch
   ``1024 * 4.65 / 370 = 12.869 um`` (written to ``lens.toml``), so every blur in pixels
   is the real sensor's blur divided by 370/1024;
4. render 8 frames focused uniformly in image distance from ``v(2000 mm)`` to
   ``v(450 mm)`` with :func:`pipeline.core.simulate.render_focal_stack` at tolerance 1e-3 (its
   plans decide layers, occlusion and magnification ``p_i / p_ref``, ``p_ref`` the mean
   position), with shot noise at 4000 e- per unit radiance and 3 e- read noise, seed 2011;
5. write ``frame_NN.png`` (16-bit sRGB), ``stack.toml``, ``lens.toml``,
   ``ground_truth.tif`` (the all-in-focus radiance at ``p_ref``, linear float32) and
   ``depth_mm.npy`` (float32, after the mapping and filling).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import tifffile
from skimage import data
from skimage.transform import downscale_local_mean

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.core import colour, optics, simulate  # noqa: E402
from pipeline.core.lens import Lens  # noqa: E402
from pipeline.core.scene import Exposure, Scene  # noqa: E402
from pipeline.io import profiles, write  # noqa: E402

OUT = ROOT / "stacks" / "motorcycle"
LENS = "fujinon-12.5mm-f1.4-sony-1-3in"
FOCAL_PX, DOFFS_PX, BASELINE_MM = 994.978, 31.086, 193.001  # quarter-scale Middlebury calib
NEAR_MM, FAR_MM = 450.0, 2000.0
FRAMES = 8
TOLERANCE = 1e-3
SEED = 2011
EXPOSURE = Exposure(electrons_at_unit=4000.0, read_noise_e=3.0)


def scene_arrays() -> tuple[np.ndarray, np.ndarray]:
    """Linear radiance (250, 370, 3) float32 and mapped depth (250, 370) mm (NaN: unknown)."""
    left, _right, disparity = data.stereo_motorcycle()
    left, disparity = left[:, :740], disparity[:, :740]
    radiance = downscale_local_mean(colour.srgb_to_linear(left / 255.0), (2, 2, 1))
    valid = np.isfinite(disparity)
    inv_depth = np.where(valid, (disparity + DOFFS_PX) / (BASELINE_MM * FOCAL_PX), 0.0)
    total = downscale_local_mean(inv_depth, (2, 2)) * 4
    count = downscale_local_mean(valid.astype(float), (2, 2)) * 4
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(count > 0, total / count, np.nan)
    lo, hi = np.nanmin(inv), np.nanmax(inv)
    mapped = 1 / FAR_MM + (inv - lo) / (hi - lo) * (1 / NEAR_MM - 1 / FAR_MM)
    return radiance.astype(np.float32), 1.0 / mapped


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    base = profiles.load_lens(LENS)
    radiance, depth = scene_arrays()
    rows, cols = depth.shape
    pitch_um = round(base.width_px * base.pixel_pitch_um / cols, 3)
    lens = Lens(
        **{
            **{k: getattr(base, k) for k in base.__dataclass_fields__ if k != "source"},
            "name": f"{base.name}, resampled to {cols}x{rows} px",
            "pixel_pitch_um": pitch_um,
            "width_px": cols,
            "height_px": rows,
        }
    )
    (OUT / "lens.toml").write_text(
        f"# {LENS} with its sensor resampled to {cols} px across (pitch "
        f"{base.width_px} * {base.pixel_pitch_um} / {cols} um); written by "
        "stacks/generate_motorcycle.py\n" + profiles.lens_to_toml(lens),
        encoding="utf-8",
    )
    scene = Scene.from_depth(radiance, depth, missing_depth="fill")
    v_far = optics.image_distance(lens.focal_length_mm, FAR_MM)
    v_near = optics.image_distance(lens.focal_length_mm, NEAR_MM)
    positions = np.linspace(v_far, v_near, FRAMES)
    start = time.perf_counter()
    frames, plans = simulate.render_focal_stack(
        scene, lens, positions, exposure_s=0.1, exposure=EXPOSURE, tolerance=TOLERANCE, seed=SEED
    )
    elapsed = time.perf_counter() - start
    print(plans[0].explain())
    print(f"rendered {FRAMES} frames in {elapsed:.1f} s")
    p_ref = float(np.mean(positions))
    lines = [
        "# Synthetic focal stack of the Middlebury 2014 Motorcycle scene (skimage copy),",
        "# rendered by stacks/generate_motorcycle.py with pipeline.simulate (see its docstring).",
        f"# Depth mapped to {NEAR_MM:g}-{FAR_MM:g} mm; magnification p/p_ref with "
        f"p_ref = {p_ref:.6f} mm",
        f"# (the mean position; ground_truth.tif is the scene at p_ref); noise "
        f"{EXPOSURE.electrons_at_unit:g} e-/unit + {EXPOSURE.read_noise_e:g} e- read, seed {SEED}.",
        'lens = "lens.toml"',
        'kind = "focal-stack"',
    ]
    for i, (frame, pos) in enumerate(zip(frames, positions)):
        name = f"frame_{i:02d}.png"
        write.write_image(OUT / name, frame, encoding="srgb16")
        lines += ["", "[[frames]]", f'file = "{name}"', f"image_distance_mm = {pos:.6f}"]
    (OUT / "stack.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    tifffile.imwrite(
        OUT / "ground_truth.tif",
        radiance,
        photometric="rgb",
        compression="zlib",
        description="flexdof transfer=linear",
        metadata=None,
    )
    np.save(OUT / "depth_mm.npy", np.nan_to_num(scene.surfaces[0].depth_mm).astype(np.float32))
    size = sum(p.stat().st_size for p in OUT.iterdir())
    print(f"wrote {OUT} ({size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
