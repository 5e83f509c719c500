"""Content beyond a sub-stack's end, judged against the frames left out of it (issue 13).

    python tests/benchmarks/held_out_ends.py --focus-stack PATH [--cases pcb7a,ambera] \
        [--flexdof-args "--method multiframe"] [--label NAME] [--work DIR] [--out FILE]

Each case (six sub-stacks of pcb7, pcb10 and amber; beetle's last seven frames leave no
content that its first three show sharper: no pixel to judge) runs ``flexdof stack`` on
some frames of a real stack, as a user with a shorter stack would; the frames left out,
focused beyond the sub-stack's end, show the content that lies beyond it sharp: a ground
truth of real photographs for the end effect of Sec. 4.1, which no frame of the sub-stack
shows in focus. The left-out frames are
registered onto the result's geometry (SIFT + RANSAC homography refined by ECC, against
the focus-selected composite of the sub-stack's frames aligned by the sidecar's
homographies, as the peers in ``real_stack_regions.py``), and so are focus-stack's results
for the same sub-stack (by default and with the frames' photometry as shot; cached in
``--work``).

The content judged: pixels, 20 px or more inside what every image covers, where a
left-out frame's local Laplacian energy (Gaussian of 8 px) is at least 4 times every
sub-stack frame's and above the left-out frames' median; there the truth is, per pixel,
the left-out frame with the most energy. Measures, in 8-bit sRGB grey:

* ``contrast``: the mean local std (31 px windows) of the image low-passed at 4 px, over
  the truth's: the haze measure of ``region_measures.py`` against the truth;
* ``band 0.7-2``, ``band 2-6``: the rms of the band-passed image (differences of Gaussians
  of those sigmas, px) over the truth's: how much of the truth's fine and coarse detail
  it holds;
* ``rms``: the rms difference to the truth, both low-passed at 2 px (the frames' noise and
  the last pixel of registration left out); it includes the left-out frames' own
  exposure and the blur of content at other depths, the same for every method.

A ratio above 1 is more than the truth holds (a stretch, or ringing); the sub-stack's own
sharpest frame (per pixel, by the same energy) is shown for its contrast. Writes a
markdown table to ``--out`` (default: stdout).
"""

from __future__ import annotations

import argparse
import glob
import json
import shlex
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import real_stack_regions as regions
from region_measures import HAZE_SIGMA_PX, HAZE_WINDOW_PX, grey

SHARED = regions.SHARED
# name: (the sub-stack, the frames left out), patterns under ../shared/data
CASES = {
    "pcb7a": ("focusstack-pcb/pcb7/pcb_00[1-5].jpg", "focusstack-pcb/pcb7/pcb_00[67].jpg"),
    "pcb7b": ("focusstack-pcb/pcb7/pcb_00[3-7].jpg", "focusstack-pcb/pcb7/pcb_00[12].jpg"),
    "pcb10a": ("focusstack-pcb/pcb10/pcb_00[0-5].JPG", "focusstack-pcb/pcb10/pcb_00[6-9].JPG"),
    "pcb10b": ("focusstack-pcb/pcb10/pcb_00[4-9].JPG", "focusstack-pcb/pcb10/pcb_00[0-3].JPG"),
    "ambera": ("shinestacker-amber/000[0-3].jpg", "shinestacker-amber/000[45].jpg"),
    "amberb": ("shinestacker-amber/000[2-5].jpg", "shinestacker-amber/000[01].jpg"),
}
ENERGY_SIGMA_PX = 8.0
SHARPER = 4.0  # a left-out frame's energy over every sub-stack frame's
INSET_PX = 20
MIN_JUDGED_PX = 1000


def energy(g: np.ndarray) -> np.ndarray:
    """Local Laplacian energy of a grey image (lightly smoothed first: noise is no focus)."""
    lap = cv2.Laplacian(cv2.GaussianBlur(g, (0, 0), 1.0), cv2.CV_32F)
    return cv2.GaussianBlur(lap * lap, (0, 0), ENERGY_SIGMA_PX)


def local_contrast(g: np.ndarray) -> np.ndarray:
    low = cv2.GaussianBlur(g, (0, 0), HAZE_SIGMA_PX)
    size = (HAZE_WINDOW_PX, HAZE_WINDOW_PX)
    mean = cv2.blur(low, size)
    return np.sqrt(np.maximum(cv2.blur(low * low, size) - mean * mean, 0))


def band(g: np.ndarray, fine: float, coarse: float) -> np.ndarray:
    return cv2.GaussianBlur(g, (0, 0), fine) - cv2.GaussianBlur(g, (0, 0), coarse)


def measures(image: np.ndarray, truth: np.ndarray, where: np.ndarray) -> dict[str, float]:
    def rms(x):
        return float(np.sqrt(np.mean(np.square(x[where]))))

    def smooth(x):
        return cv2.GaussianBlur(x, (0, 0), 2.0)

    def contrast(x):
        return float(local_contrast(x)[where].mean())

    return {
        "contrast": contrast(image) / contrast(truth),
        "band 0.7-2": rms(band(image, 0.7, 2.0)) / rms(band(truth, 0.7, 2.0)),
        "band 2-6": rms(band(image, 2.0, 6.0)) / rms(band(truth, 2.0, 6.0)),
        "rms": rms(smooth(image) - smooth(truth)),
    }


def evaluate(name: str, work: Path, binary: str | None, extra: list[str], label: str) -> dict:
    sub, held = CASES[name]
    result = work / f"{name}_{label}.tif"
    files = sorted(glob.glob(str(SHARED / sub)))
    subprocess.run(["flexdof", "stack", *files, "-o", str(result), "-q", *extra], check=True)
    side = json.loads(Path(str(result) + ".json").read_text())
    flex = regions.read_srgb(result)
    shape = flex.shape[:2]
    frames, valid = [], np.ones(shape, bool)
    for meta, path in zip(side["frames"], side["inputs"]):
        frame, cover = regions.warp(
            regions.read_srgb(Path(path)), np.array(meta["homography"]), shape
        )
        frames.append(frame)
        valid &= cover
    composite = regions.frames_composite(frames)

    def registered(path: Path) -> np.ndarray:
        nonlocal valid
        image = regions.read_srgb(path)
        h, _ = regions.register(image, composite)
        image, cover = regions.warp(image, h, shape)
        valid &= cover
        return image

    truths = [grey(registered(Path(p))) for p in sorted(glob.glob(str(SHARED / held)))]
    methods = {"flexdof": grey(flex)}
    for peer, as_shot in (("focus-stack", False), (regions.AS_SHOT_PEER, True)):
        path = regions.run_focus_stack(name, sub, work, binary, as_shot=as_shot)
        if path is not None:
            methods[peer] = grey(registered(Path(path)))
    greys = [grey(f) for f in frames]
    frame_energy = np.stack([energy(g) for g in greys])
    truth_energy = np.stack([energy(g) for g in truths])
    best = np.argmax(truth_energy, axis=0)[None]
    most = np.take_along_axis(truth_energy, best, 0)[0]
    truth = np.take_along_axis(np.stack(truths), best, 0)[0]
    inset = np.ones((2 * INSET_PX + 1,) * 2, np.uint8)
    inside = cv2.erode(valid.astype(np.uint8), inset) > 0
    where = inside & (most > SHARPER * frame_energy.max(axis=0))
    where &= most > np.median(most[inside])
    if where.sum() < MIN_JUDGED_PX:
        raise SystemExit(f"{name}: the left-out frames show nothing sharper than the sub-stack")
    sharpest = np.take_along_axis(np.stack(greys), np.argmax(frame_energy, axis=0)[None], 0)[0]
    return {
        "share": float(where.mean()),
        "ends": side.get("frame_range", {}).get("beyond_ends", []),
        "scores": {m: measures(img, truth, where) for m, img in methods.items()},
        "sub-stack frames": measures(sharpest, truth, where)["contrast"],
    }


def report(results: dict, label: str) -> str:
    lines = [
        f"# Content beyond a sub-stack's end against the frames left out ({label})",
        "",
        "`python tests/benchmarks/held_out_ends.py` (see its docstring). Ratios to the "
        "left-out frames (1: as much as the truth holds); rms in 8-bit sRGB levels.",
        "",
        "| case | judged | method | contrast | band 0.7-2 | band 2-6 | rms |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        for m, s in r["scores"].items():
            lines.append(
                f"| {name} | {r['share']:.1%} | {m} | {s['contrast']:.3f} | "
                f"{s['band 0.7-2']:.3f} | {s['band 2-6']:.3f} | {s['rms']:.2f} |"
            )
        lines.append(
            f"| {name} | {r['share']:.1%} | the sub-stack's sharpest frame | "
            f"{r['sub-stack frames']:.3f} | | | |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--focus-stack", help="focus-stack's binary (build-focus-stack.sh)")
    parser.add_argument("--flexdof-args", default="", help="more arguments of flexdof stack")
    parser.add_argument("--label", default="default", help="names the results")
    parser.add_argument("--work", type=Path, default=Path("/tmp/flexdof-held-out"))
    parser.add_argument("--out", type=Path, help="the markdown table (default: stdout)")
    args = parser.parse_args(argv)
    if not SHARED.is_dir():
        raise SystemExit(f"{SHARED}: the shared sample data is not there")
    args.work.mkdir(parents=True, exist_ok=True)
    extra = shlex.split(args.flexdof_args)
    results = {}
    for name in args.cases.split(","):
        if name not in CASES:
            raise SystemExit(f"--cases: {name!r} is none of {', '.join(CASES)}")
        results[name] = evaluate(name, args.work, args.focus_stack, extra, args.label)
        print(f"{name}: done", file=sys.stderr, flush=True)
    text = report(results, args.label)
    if args.out:
        args.out.write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps(results, indent=1))
    else:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
