"""The accuracy benchmark's scenes with ground truth: the shipped motorcycle sample and
generated scenes with depth edges, written as focal stacks.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import dask
import numpy as np

from pipeline.core import align, colour, lens, optics, simulate, stack_kernel
from pipeline.core.scene import Exposure, Scene
from pipeline.core.weights import constant_speed_weights
from pipeline.io import profiles, write
from pipeline.io.stackfile import check_frames, image_distances_mm, load_stack
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import read_previews
from pipeline.parallel import accumulate

MOTORCYCLE = profiles.shipped("sample")
REFERENCE_THETA_ORDER = 64
SEC41_LENS = "fujinon-12.5mm-f1.4-sony-1-3in"
NEAR_MM, FAR_MM = 450.0, 2000.0
NOISE = Exposure(electrons_at_unit=4000.0, read_noise_e=3.0)  # as stacks/motorcycle


# ----------------------------------------------------------------------------- scenes
def edges_scene(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Radiance (rows, cols, 3) float32 and depth (mm) of a scene with depth edges.

    A far plane (2000 mm), a slanted floor (1400 -> 700 mm, linear in inverse depth),
    a disk at 800 mm and a near rectangle at 450 mm, each textured with a different
    photograph bundled with scikit-image (linearised sRGB).
    """
    from skimage import data
    from skimage.transform import resize

    rows, cols = shape

    def texture(image):
        return colour.srgb_to_linear(resize(image / 255.0, (rows, cols), anti_aliasing=True))

    radiance = texture(data.astronaut())
    depth = np.full(shape, FAR_MM)
    r, c = np.mgrid[0:rows, 0:cols]
    floor = r >= int(0.7 * rows)
    frac = np.clip((r - 0.7 * rows) / (0.3 * rows), 0.0, 1.0)
    depth = np.where(floor, 1.0 / (1 / 1400 + frac * (1 / 700 - 1 / 1400)), depth)
    radiance = np.where(floor[..., None], texture(data.rocket()), radiance)
    disk = (r - 0.4 * rows) ** 2 + (c - 0.72 * cols) ** 2 <= (0.22 * rows) ** 2
    depth = np.where(disk, 800.0, depth)
    radiance = np.where(disk[..., None], texture(data.chelsea()), radiance)
    rect = (r >= 0.15 * rows) & (r < 0.6 * rows) & (c >= 0.08 * cols) & (c < 0.4 * cols)
    depth = np.where(rect, NEAR_MM, depth)
    radiance = np.where(rect[..., None], texture(data.coffee()), radiance)
    return radiance.astype(np.float32), depth


def scene_lens(shape: tuple[int, int]) -> lens.Lens:
    """The motorcycle sample's lens (12.5 mm f/1.4, 12.869 um pixels) on a ``shape`` sensor."""
    base = profiles.load_lens(MOTORCYCLE / "lens.toml")
    return dataclasses.replace(base, width_px=shape[1], height_px=shape[0], source=None)


def stack_positions(lens: lens.Lens, frames: int) -> np.ndarray:
    """``frames`` focus positions uniform in image distance over 2000..450 mm."""
    v_far = optics.image_distance(lens.focal_length_mm, FAR_MM)
    v_near = optics.image_distance(lens.focal_length_mm, NEAR_MM)
    return np.linspace(v_far, v_near, frames)


def write_stack(
    directory: Path,
    radiance: np.ndarray,
    depth: np.ndarray,
    lens: lens.Lens,
    frames: int,
    *,
    noisy: bool,
    tolerance: float,
    seed: int = 7,
) -> Path:
    """Render a focal stack of the scene into ``directory`` (float32 TIFFs + stack.toml).

    ``p_ref`` is the middle frame's position (the engine's reference), so the radiance
    itself is the ground truth of the aligned result.
    """
    directory.mkdir(parents=True, exist_ok=True)
    positions = stack_positions(lens, frames)
    scene = Scene.from_depth(radiance, depth)
    images, _ = simulate.render_focal_stack(
        scene,
        lens,
        positions,
        exposure_s=0.1,
        exposure=NOISE if noisy else None,
        reference_image_distance_mm=float(positions[frames // 2]),
        tolerance=tolerance,
        seed=seed,
    )
    (directory / "lens.toml").write_text(profiles.lens_to_toml(lens), encoding="utf-8")
    lines = ['lens = "lens.toml"', 'kind = "focal-stack"']
    for i, (image, pos) in enumerate(zip(images, positions)):
        name = f"frame_{i:02d}.tif"
        write.write_image(directory / name, image, encoding="float32")
        lines += ["", "[[frames]]", f'file = "{name}"', f"image_distance_mm = {pos:.9f}"]
    (directory / "stack.toml").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return directory


@dataclasses.dataclass
class Prepared:
    """A stack taken to the deconvolution step with the default options."""

    name: str
    directory: Path
    truth: np.ndarray
    positions: np.ndarray
    average: np.ndarray
    clipped: np.ndarray
    kernel: np.ndarray
    samples: np.ndarray


def prepare(name: str, directory: Path, truth: np.ndarray) -> Prepared:
    """Align (default: estimated), weight and average a stack; its Sec. 9 kernel."""
    options = StackOptions()
    stack = load_stack(directory)
    lens = stack.lens_profile
    shape = check_frames(stack).shape
    positions = image_distances_mm(stack, lens).image_distances_mm
    weights = constant_speed_weights(positions, ends=options.sweep_ends)
    homographies = _estimated(stack.files, shape, options.align_max_side_px)
    graph = accumulate.weighted_sum_graph(stack.files, homographies, weights, shape)
    (summed,) = dask.compute(graph)
    average, clipped = summed[0], summed[1]
    kernel, samples, _ = stack_kernel.stack_kernel(
        positions, weights, lens=lens, absolute=True, blur_span_px=None
    )
    return Prepared(name, directory, truth, positions, average, clipped, kernel, samples)


def _estimated(
    files, shape, max_side_px: int, model: str = StackOptions.align_model
) -> list[np.ndarray]:
    previews = read_previews(files, max_side_px)
    found = align.estimate_alignment(previews, model=model, max_side_px=max_side_px)
    return [align.rescale_homography(a.homography, previews[0].shape, shape[:2]) for a in found]
