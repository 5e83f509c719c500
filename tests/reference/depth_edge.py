"""A near textured plane in front of a far one, ray traced with occlusion and the lens's
breathing (:mod:`reference.raytrace`, independent of ``pipeline.simulate``): the depth-edge
focal stack of issue 13 (``tests/benchmarks/synthetic_guard.py``, ``tests/test_gcv.py``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.io.write import write_image
from reference import raytrace
from reference.cases import texture

EDGE_LENS = """name = "12.5 mm f/1.4, 20 um pixels (the reference suite's lens)"
focal_length_mm = 12.5
f_number = 1.4

[sensor]
pixel_pitch_um = 20.0
width_px = {cols}
height_px = {rows}
shutter = "global"
line_time_us = 0.0

[psf]
model = "pillbox"
gaussian_g = 1.0

[focus]
mechanism = "detector"
max_speed_mm_s = 2.7
travel_mm = 15.0
"""


def depth_edge(folder: Path, noise: float, shape=(128, 192)):
    """Write the stack to ``folder`` (9 frames focused from 400 to 2500 mm, float32 TIFFs,
    ``stack.toml`` with image distances and ``lens.toml``): two 1/f textures at 500 mm
    (left, in front) and 1500 mm, white noise of ``noise``. Returns the truth, the frame
    files and masks of the pixels within 12 px of the edge and beyond 24 px of it."""
    rows, cols = shape
    edge = cols // 2
    near, far = texture(shape, 20), texture(shape, 21)
    f_mm, f_number, pitch_mm = 12.5, 1.4, 0.020
    positions = [f_mm * u / (u - f_mm) for u in np.geomspace(400.0, 2500.0, 9)]
    p_ref = positions[4]
    rng = np.random.default_rng(7)
    lines = ['lens = "lens.toml"', 'kind = "focal-stack"', ""]
    for i, p in enumerate(positions):
        frame = raytrace.render_edge(near, far, edge, 500.0, 1500.0, f_mm=f_mm,
                                     f_number=f_number, pitch_mm=pitch_mm, times_s=[0.0, 1.0],
                                     positions_mm=[p, p], p_ref_mm=p_ref)
        if noise:
            frame = frame + rng.normal(0, noise, frame.shape)
        name = f"frame_{i:02d}.tif"
        write_image(folder / name, np.clip(frame, 0, None).astype(np.float32), encoding="float32")
        lines += ["[[frames]]", f'file = "{name}"', f"image_distance_mm = {float(p)!r}", ""]
    (folder / "stack.toml").write_text("\n".join(lines))
    (folder / "lens.toml").write_text(EDGE_LENS.format(rows=rows, cols=cols))
    truth = np.where(np.arange(cols)[None, :] < edge, near, far).astype(np.float32)
    distance = np.abs(np.arange(cols)[None, :] - edge + 0.5).repeat(rows, 0)
    inner = np.zeros(shape, bool)
    inner[16:-16, 16:-16] = True
    regions = {"near edge": (distance <= 12) & inner, "away": (distance > 24) & inner}
    return truth, sorted(folder.glob("frame_*.tif")), regions
