"""The region measures on stacks with a ground truth: what a perfect all-in-focus image scores
against focus-stack, beside flexdof (issue 13).

    python tests/benchmarks/regions_vs_truth.py --focus-stack PATH [--out DIR] [--work DIR] \
        [--scenes board,board_45px_3frames,...]

Real photographs have no truth, so ``real_stack_regions.py`` judges flexdof against
focus-stack and the frames alone. This benchmark renders stacks of scenes whose all-in-focus
image is known, writes their frames as 8-bit sRGB PNGs with no metadata (a photographer's
folder: no lens, no focus positions), runs ``flexdof stack`` (the default, and the quality
method ``--method multiframe``), focus-stack and enfuse (when installed) on those files as
``real_stack_regions.py`` does, and scores the truth itself as one more image, registered the
same way. So the tables show, per region and measure, where the truth lies: a result that
beats the truth on haze shows more low-frequency contrast than the scene has.

Scenes (``pipeline.simulate``: layered pillbox PSFs with occlusion, the lens's breathing,
shot noise at 4000 e- per unit radiance and 3 e- read noise; ``SCENES``):

* ``board``: a tilted textured board (six skimage photographs in a 512x768 mosaic), 300 mm
  at the bottom to 420 mm at the top, with a raised block at 280 mm (beyond the near end);
  nine frames focused over 300-420 mm; the Sigma 30 mm f/1.4 profile with its pixels
  scaled so that the range spans 11.3 px of blur; breathing moves the corners by 7 px;
* ``board_ends``: the same, frames focused over 320-400 mm only, so content lies beyond
  both ends of the sweep (as in every real stack here);
* ``board_22px``, ``board_45px``: the first with two and four times the blur;
* ``board_5frames``, ``board_6frames``, ``board_7frames``: shorter stacks (7.4, 18.7 and
  29.8 px of blur, content beyond one or both ends);
* ``board_iso3200``: ``board`` with the noise of an APS-C sensor at ISO 3200 (780 e- per
  unit radiance, 3 e- read noise: 0.015 in linear light at mid-grey), the case where the
  Wiener filter's noise limit holds the result (``pipeline.core.frame_support.
  visible_noise_limit``);
* ``motorcycle``: the shipped sample, its 16-bit frames rounded to 8 bits;
* with ``--scenes`` only (``FEW_FRAMES``, not in the default run): ``board_45px_3frames``,
  ``_4frames``, ``_5frames`` and ``board_22px_3frames``, ``board_45px`` and ``board_22px``
  with three to five frames over the same range, 11-23 px of blur between neighbouring
  frames: stacks too sparse for the sweep Sec. 9 emulates, where the average's blur varies
  with depth between the frames
  (``results/regions_vs_truth/few_frames/regions_vs_truth.md``).

The summary also gives the blur span ``flexdof stack`` fitted (the frames carry no focus
positions) against the one the scene was rendered with.

Writes ``DIR/regions_vs_truth.md`` (the summary, then ``real_stack_regions.py``'s tables
with truth and multiframe columns) and crops flexdof | focus-stack | sharpest frame | truth |
multiframe (``DIR/NAME_regions.png``, ``DIR/NAME_maxdiff.png``). Rendered frames, results and the
peer's output are cached in ``--work``.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

import cv2
import numpy as np
from skimage import data

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_stack_regions import (  # noqa: E402
    AS_SHOT_PEER,
    evaluate,
    good_regions,
    output_folders,
    report,
    run_flexdof,
)
from region_measures import MEASURES, verdict  # noqa: E402

from pipeline.core import colour, optics, simulate  # noqa: E402
from pipeline.core.lens import Lens  # noqa: E402
from pipeline.core.scene import Exposure, Scene  # noqa: E402
from pipeline.io import profiles  # noqa: E402
from pipeline.io.read import read_frame  # noqa: E402
from pipeline.io.stackfile import image_distances_mm, load_stack  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "regions_vs_truth"
EXPOSURE = Exposure(electrons_at_unit=4000.0, read_noise_e=3.0)
PNG = [cv2.IMWRITE_PNG_COMPRESSION, 6]
MULTIFRAME = ["--method", "multiframe"]  # the quality method, scored as one more image


@dataclasses.dataclass(frozen=True)
class Board:
    """A tilted-board stack: ``frames`` frames focused from ``far_mm`` to ``near_mm``,
    the lens's pixels ``pitch`` times the sensor's width per board column."""

    pitch: float
    frames: int
    near_mm: float
    far_mm: float
    exposure: Exposure = EXPOSURE


# 300-420 mm spans 11.3 px of blur at pitch 2, 22.6 at 1, 45.2 at 0.5
SCENES = {
    "board": Board(2.0, 9, 300.0, 420.0),
    "board_ends": Board(2.0, 9, 320.0, 400.0),
    "board_22px": Board(1.0, 9, 300.0, 420.0),
    "board_45px": Board(0.5, 9, 300.0, 420.0),
    "board_5frames": Board(2.0, 5, 320.0, 400.0),
    "board_6frames": Board(1.0, 6, 310.0, 410.0),
    "board_7frames": Board(0.5, 7, 320.0, 400.0),
    # as an APS-C sensor at ISO 3200 (camera_variants.py's "high ISO"): 780 e- at white
    "board_iso3200": Board(2.0, 9, 300.0, 420.0, Exposure(780.0, 3.0)),
    "motorcycle": None,  # the shipped sample
}
DEFAULT_SCENES = tuple(SCENES)
# sparse stacks, run with --scenes only: 45 and 22 px of blur over three to five frames
FEW_FRAMES = {
    "board_45px_3frames": Board(0.5, 3, 300.0, 420.0),
    "board_45px_4frames": Board(0.5, 4, 300.0, 420.0),
    "board_45px_5frames": Board(0.5, 5, 300.0, 420.0),
    "board_22px_3frames": Board(1.0, 3, 300.0, 420.0),
}
SCENES.update(FEW_FRAMES)


def board_radiance() -> np.ndarray:
    """Linear radiance (512, 768, 3): six 256 px skimage photographs, three by two."""
    tiles = [
        data.astronaut()[0:256, 150:406],
        data.coffee()[100:356, 100:356],
        data.chelsea()[0:256, 100:356],
        data.rocket()[100:356, 200:456],
        data.immunohistochemistry()[100:356, 100:356],
        data.astronaut()[256:512, 200:456],
    ]
    mosaic = np.concatenate(
        [np.concatenate(tiles[:3], axis=1), np.concatenate(tiles[3:], axis=1)], axis=0
    )
    return colour.srgb_to_linear(mosaic.astype(np.float32) / 255)


def board_lens(board: Board, cols: int, rows: int) -> Lens:
    """The Sigma 30 mm f/1.4 profile with pixels ``board.pitch`` x sensor width / cols."""
    base = profiles.load_lens("sigma-30mm-f1.4-canon-eos-20d")
    pitch = board.pitch * base.pixel_pitch_um * base.width_px / cols
    return dataclasses.replace(base, pixel_pitch_um=pitch, width_px=cols, height_px=rows)


def render_board(board: Board) -> tuple[np.ndarray, np.ndarray, float]:
    """Frames (linear, ``(n, 512, 768, 3)``), the truth (the scene at the mean position,
    as the simulator's frames are) and the true blur span (px)."""
    radiance = board_radiance()
    rows, cols = radiance.shape[:2]
    lens = board_lens(board, cols, rows)
    depth = 1 / np.linspace(1 / 420, 1 / 300, rows)[:, None] * np.ones((1, cols))
    depth[300:420, 300:480] = 280.0  # a raised block, nearer than the near end
    v_far = optics.image_distance(lens.focal_length_mm, board.far_mm)
    v_near = optics.image_distance(lens.focal_length_mm, board.near_mm)
    frames, _ = simulate.render_focal_stack(
        Scene.from_depth(radiance, depth),
        lens,
        np.linspace(v_far, v_near, board.frames),
        exposure_s=0.1,
        exposure=board.exposure,
        tolerance=1e-3,
        seed=2011,
    )
    return frames, radiance, float(lens.blur_px(v_near, v_far))


def motorcycle() -> tuple[list[np.ndarray], np.ndarray, float]:
    """The shipped sample's frames, truth and true blur span (its lens and positions)."""
    sample = TESTS.parent / "stacks" / "motorcycle"
    stack = load_stack(sample)
    positions = image_distances_mm(stack).image_distances_mm
    span = float(stack.lens_profile.blur_px(positions.min(), positions.max()))
    frames = [read_frame(p) for p in stack.files]
    return frames, read_frame(sample / "ground_truth.tif"), span


def write_srgb8(path: Path, linear: np.ndarray) -> None:
    """An 8-bit sRGB PNG of a linear RGB image (as a camera's JPEG would encode it)."""
    encoded = colour.linear_to_srgb(np.clip(linear, 0, 1))
    cv2.imwrite(str(path), np.round(255 * encoded).astype(np.uint8)[..., ::-1], PNG)


def prepare(name: str, work: Path) -> tuple[str, Path, float]:
    """The scene's frames as 8-bit PNGs (a glob), its truth and its true blur span,
    rendered once into ``work``."""
    folder = work / name
    truth = folder / "truth.png"
    span_file = folder / "span_px.txt"
    pattern = str(folder / "frames" / "frame_*.png")
    if truth.exists() and span_file.exists():
        return pattern, truth, float(span_file.read_text())
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    if SCENES[name] is None:
        frames, sharp, span = motorcycle()
    else:
        print(f"rendering {name} (about a minute)", flush=True)
        frames, sharp, span = render_board(SCENES[name])
    for i, frame in enumerate(frames):
        write_srgb8(folder / "frames" / f"frame_{i:02d}.png", frame)
    write_srgb8(truth, sharp)
    span_file.write_text(f"{span:.4f}\n")
    return pattern, truth, span


def summary(results: dict) -> list[str]:
    """Per scene: the blur span fitted against the true one, regions flexdof and the truth
    are at least as good as focus-stack on all four measures, the truth's losses to
    focus-stack per measure, and PSNR against the truth."""
    lines = [
        "| scene | blur span px: true | fitted | regions >= focus-stack on all 4: flexdof | "
        "the truth | the truth's losses to focus-stack (sharpness/halo/haze/noise) | the "
        "same against focus-stack as shot: flexdof | the truth | the truth's losses | PSNR "
        "against the truth: flexdof | flexdof --method multiframe | focus-stack | "
        "focus-stack as shot | enfuse |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, res in results.items():
        s = res["scores"]
        psnr = res["psnr_against"]["truth"]
        true, fitted = res["true_span_px"], res["blur_span_px"]
        cells = []
        for peer in ("focus-stack", AS_SHOT_PEER):
            if peer not in s:
                cells += ["-", "-", "-"]
                continue
            losses = [
                sum(verdict(m, s["truth"][m][r], s[peer][m][r]) == "loss" for r in range(9))
                for m in MEASURES
            ]
            cells += [
                f"{good_regions(s, peer)[0]}/9",
                f"{good_regions(s, peer, method='truth')[0]}/9",
                "/".join(map(str, losses)),
            ]
        lines.append(
            f"| {name} | {true:.1f} | {fitted:.1f} ({fitted / true - 1:+.0%}) | "
            + " | ".join(cells)
            + " | "
            + " | ".join(
                f"{psnr[k]:.2f}" if k in psnr else "-"
                for k in ("flexdof", "multiframe", "focus-stack", AS_SHOT_PEER, "enfuse")
            )
            + " |"
        )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--focus-stack",
        required=True,
        metavar="PATH",
        help="the focus-stack binary (bash ../shared/tools/build-focus-stack.sh)",
    )
    parser.add_argument("--flexdof-args", default="--threads 2")
    parser.add_argument("--scenes", default=",".join(DEFAULT_SCENES),
                        help=f"default: all but {', '.join(FEW_FRAMES)}")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--work", type=Path, help="renders and results (default OUT/work)")
    args = parser.parse_args()
    work = output_folders(args)
    results = {}
    for name in args.scenes.split(","):
        if name not in SCENES:
            raise SystemExit(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
        pattern, truth, span = prepare(name, work)
        flexdof_args = shlex.split(args.flexdof_args)
        result = run_flexdof(name, pattern, work, flexdof_args)
        quality = run_flexdof(f"{name}_multiframe", pattern, work, [*flexdof_args, *MULTIFRAME])
        extra = {"truth": truth, "multiframe": quality}
        results[name] = evaluate(name, pattern, result, work, args.out, args.focus_stack, extra)
        results[name]["true_span_px"] = span
        print("\n".join(summary({name: results[name]})[2:]), flush=True)
    text = report(results, args).split("\n", 2)[2]  # its tables, under this file's heading
    head = [
        "# The region measures against a ground truth (issue 13)",
        "",
        f"`python tests/benchmarks/regions_vs_truth.py --focus-stack PATH` (flexdof args "
        f"`{args.flexdof_args}`). The truth is scored as one more image: where it loses to "
        "focus-stack, focus-stack shows what the scene does not have. PSNR in 8-bit sRGB levels "
        "over the common area, after registration (which resamples the truth and the peer).",
        "",
        *summary(results),
        "",
    ]
    (args.out / "regions_vs_truth.md").write_text("\n".join(head) + "\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
