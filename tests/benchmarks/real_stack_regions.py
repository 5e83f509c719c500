"""Real stacks, region by region: flexdof against focus-stack, enfuse and the sharpest frame.

    python tests/benchmarks/real_stack_regions.py [--stacks pcb7,beetle] \
        [--flexdof-args "--method wiener"] [--result pcb7=out.tif] [--out DIR] [--work DIR] \
        [--focus-stack PATH]

For each stack: runs ``flexdof stack`` as a user would (or takes ``--result
NAME=FILE``, whose ``FILE.json`` sidecar must sit next to it), warps every frame
into the result's geometry with the sidecar's homographies, registers the peers'
results to that geometry (SIFT + RANSAC homography refined by ECC against a
focus-selected composite of those frames; focus-stack crops and rescales its
output), splits the common area into a 3x3 grid and
measures per region sharpness, halo, haze and noise (see ``region_measures.py``
for what they are and why they cannot be gamed) of flexdof, focus-stack (and, given
``--focus-stack PATH``, focus-stack with the frames' photometry as shot: its contrast and
white-balance matching off, see :func:`run_focus_stack`), enfuse (``align_image_stack
-m`` + ``enfuse --contrast-weight=1 --hard-mask``, when installed; cached in
``DIR/work``), the region's sharpest aligned frame and
the frames' composite (per pixel the aligned frame with the most Laplacian energy: a plain
focus stacker made of the frames' own pixels; the summary counts the regions where it is at
least as good as focus-stack on haze, a check of how far that measure rewards more than the
frames show).

Writes ``DIR/real_regions.md`` (per stack and measure: values per region and
flexdof's verdict against focus-stack; the count of regions where flexdof is at
least as good on every measure), ``DIR/real_regions.json`` and crops at 1:1
pixels, flexdof | focus-stack | sharpest frame: ``DIR/NAME_maxdiff.png`` (the
window where flexdof and focus-stack differ most) and ``DIR/NAME_regions.png``
(the most different window of each region, laid out as the 3x3 grid).
"""

from __future__ import annotations

import argparse
import glob
import json
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from pipeline.io.orientation import upright

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_stacks import SHARED, STACKS  # the same four stacks as the sharpness benchmark
from region_measures import (
    GRID,
    MEASURES,
    TIES,
    UNITS,
    Reference,
    at_least_as_good,
    verdict,
)

FOCUS_STACK = SHARED / "peer-results" / "focus-stack"
REGION_NAMES = [
    "top-left",
    "top",
    "top-right",
    "left",
    "centre",
    "right",
    "bottom-left",
    "bottom",
    "bottom-right",
]
ENFUSE_ARGS = [
    "--exposure-weight=0",
    "--saturation-weight=0",
    "--contrast-weight=1",
    "--hard-mask",
    "--contrast-window-size=9",
]
AS_SHOT = ["--no-contrast", "--no-whitebalance"]  # focus-stack without its photometric match
# a peer's result that registers to the aligned frames' composite below this ECC is not the
# scene any more (pieces misaligned by its own alignment): it is reported, not scored (the
# peers of the real stacks register at 0.976-0.990)
USABLE_REGISTRATION = 0.9
AS_SHOT_PEER = "focus-stack as shot"
CROP_PX = 192
PNG = [cv2.IMWRITE_PNG_COMPRESSION, 9]


# ----------------------------------------------------------------------------- images
def read_srgb(path: Path) -> np.ndarray:
    """An image as float32 RGB sRGB code values 0-255 (float TIFFs are linear: encoded)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SystemExit(f"cannot read {path}")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    image = image[..., :3][..., ::-1]
    if image.dtype == np.uint8:
        return image.astype(np.float32)
    if image.dtype == np.uint16:
        return image.astype(np.float32) / 257.0
    linear = np.clip(image.astype(np.float32), 0, 1)
    encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    return (255 * encoded).astype(np.float32)


def warp(image: np.ndarray, h: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """``out(H x) = image(x)`` on a grid of ``shape``; and where it is covered."""
    size = (shape[1], shape[0])
    out = cv2.warpPerspective(
        image, h, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    ones = np.ones(image.shape[:2], np.float32)
    cover = cv2.warpPerspective(
        ones, h, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )
    return out, cover > 0.999


def _psnr(image: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    """PSNR (dB, peak 255) of ``image`` against ``truth`` over the pixels ``where``."""
    mse = float(np.mean((image[where] - truth[where]) ** 2))
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))


def to_u8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def register(
    moving: np.ndarray, fixed: np.ndarray, max_side: int = 1200
) -> tuple[np.ndarray, float]:
    """Homography mapping ``moving``'s pixels onto ``fixed``'s, and the ECC correlation."""
    scale = min(1.0, max_side / max(fixed.shape[:2]))
    m_scale = min(1.0, max_side / max(moving.shape[:2]))

    def small(img, s):
        g = cv2.cvtColor(to_u8(img), cv2.COLOR_RGB2GRAY)
        return cv2.resize(g, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else g

    a, b = small(moving, m_scale), small(fixed, scale)
    sift = cv2.SIFT_create(5000)
    ka, da = sift.detectAndCompute(a, None)
    kb, db = sift.detectAndCompute(b, None)
    matches = cv2.BFMatcher().knnMatch(da, db, k=2)
    good = [m for m, n in (p for p in matches if len(p) == 2) if m.distance < 0.75 * n.distance]
    src = np.float32([ka[m.queryIdx].pt for m in good])
    dst = np.float32([kb[m.trainIdx].pt for m in good])
    h, _ = cv2.findHomography(src, dst, cv2.RANSAC, 3.0)
    # refine with ECC (on smoothed grey; maps fixed coords -> moving coords)
    warp_m = np.linalg.inv(h).astype(np.float32)
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-6)
    try:
        cc, warp_m = cv2.findTransformECC(
            b.astype(np.float32),
            a.astype(np.float32),
            warp_m,
            cv2.MOTION_HOMOGRAPHY,
            criteria,
            None,
            5,
        )
        h = np.linalg.inv(warp_m.astype(np.float64))
    except cv2.error:
        cc = float("nan")
    up = np.diag([1 / scale, 1 / scale, 1.0])
    down = np.diag([m_scale, m_scale, 1.0])
    full = up @ h @ down
    return full / full[2, 2], float(cc)


# ----------------------------------------------------------------------------- producers
def frames_composite(frames: list[np.ndarray]) -> np.ndarray:
    """Per pixel the aligned (RGB) frame with the most Laplacian energy (smoothed over
    4 px): a plain focus stacker made of the frames' own pixels."""
    energy = [
        cv2.GaussianBlur(cv2.Laplacian(f.mean(axis=-1), cv2.CV_32F) ** 2, (0, 0), 4.0)
        for f in frames
    ]
    choice = np.argmax(np.stack(energy), axis=0)
    return np.take_along_axis(np.stack(frames), choice[None, ..., None], axis=0)[0]


def run_flexdof(name: str, pattern: str, work: Path, extra: list[str]) -> Path:
    out = work / f"{name}_flexdof.tif"
    files = sorted(glob.glob(str(SHARED / pattern)))
    cmd = ["flexdof", "stack", *files, "-o", str(out), *extra]
    print("$", " ".join(cmd[:3]), "...", " ".join(cmd[-2 - len(extra) :]), flush=True)
    subprocess.run(cmd, check=True)
    return out


def run_focus_stack(
    name: str, pattern: str, work: Path, binary: str | None, *, as_shot: bool = False
) -> Path | None:
    """focus-stack's result: the shared one for the four stacks (made as in its
    SOURCE.txt), else made here with ``binary`` the same way and cached; None without.

    ``as_shot``: run with ``AS_SHOT`` (the frames' photometry as shot: no contrast and
    white-balance matching), made here only (needs ``binary``). focus-stack matches every
    frame's brightness to the middle frame's with a quadratic gain map over the image and
    a gain and offset per channel, fitted on 64x64 block means of the 8-bit sRGB frames
    (``task_align.cc``, ``match_contrast``, ``match_whitebalance``). In sRGB, a block holding
    a sharp highlight reads darker than the same block defocused (the encoding is concave),
    so the match lifts each frame where it is the sharpest: a contrast stretch that the
    truth itself loses to on haze (``regions_vs_truth.py``)."""
    shared = FOCUS_STACK / f"{name}.png"
    if shared.exists() and not as_shot:
        return shared
    out = work / f"{name}_focus-stack{'-as-shot' if as_shot else ''}.png"
    if out.exists() or _failed(out).exists() or binary is None:
        return out if out.exists() else None
    files = sorted(glob.glob(str(SHARED / pattern)))
    flags = AS_SHOT if as_shot else []
    ok = _attempt(name, AS_SHOT_PEER if as_shot else "focus-stack", out,
                  [binary, *flags, f"--output={out}", *files])  # fmt: skip
    return out if ok else None


def _failed(out: Path) -> Path:
    """Where a peer's refusal to make ``out`` is recorded (what it said)."""
    return out.with_name(out.name + ".failed")


def _attempt(name: str, peer: str, out: Path, argv: list[str]) -> bool:
    """Run a peer's command; where it gives up (an error exit, or no ``out``: focus-stack
    exits 0 on some failures), record the line that says why in ``_failed(out)``."""
    done = subprocess.run(argv, capture_output=True)
    if done.returncode == 0 and out.exists():
        return True
    # what it said on stderr, without progress lines (focus-stack's "[ 3/41] ...") and
    # align_image_stack's closing "Exiting...": its last paragraph
    said = [ln.strip() for ln in done.stderr.decode(errors="replace").splitlines()]
    said = [ln for ln in said if not ln.startswith("[") and ln != "Exiting..."]
    paragraphs = " ".join(ln or "\n" for ln in said).split("\n")
    last = [par.strip() for par in paragraphs if par.strip()]
    reason = last[-1] if last else f"exit code {done.returncode}"
    _failed(out).write_text(f"{Path(argv[0]).name}: {reason}\n")
    print(f"{name}: {peer} gave no result: {reason}", flush=True)
    return False


def peer_failures(name: str, work: Path) -> dict[str, str]:
    """What each peer said where it gave up on ``name`` (peer name -> its message)."""
    outs = {
        "focus-stack": work / f"{name}_focus-stack.png",
        AS_SHOT_PEER: work / f"{name}_focus-stack-as-shot.png",
        "enfuse": work / f"{name}_enfuse.tif",
    }
    return {peer: _failed(o).read_text().strip() for peer, o in outs.items() if _failed(o).exists()}


def run_enfuse(name: str, pattern: str, work: Path) -> Path | None:
    """Cached align_image_stack + enfuse result, or None when they are not installed or
    give up (what they said is recorded, see :func:`peer_failures`)."""
    out = work / f"{name}_enfuse.tif"
    if out.exists() or _failed(out).exists():
        return out if out.exists() else None
    if not (shutil.which("align_image_stack") and shutil.which("enfuse")):
        return None
    files = sorted(glob.glob(str(SHARED / pattern)))
    tmp = work / f"{name}_enfuse_aligned"
    tmp.mkdir(parents=True, exist_ok=True)
    first = tmp / "al_0000.tif"  # align_image_stack's first aligned frame
    argv = ["align_image_stack", "-m", "--use-given-order", "-a", str(tmp / "al_"), *files]
    if _attempt(name, "enfuse", first, argv):
        aligned = sorted(str(p) for p in tmp.glob("al_*.tif"))
        _attempt(name, "enfuse", out, ["enfuse", *ENFUSE_ARGS, "-o", str(out), *aligned])
    else:
        _failed(first).rename(_failed(out))
    shutil.rmtree(tmp)
    return out if out.exists() else None


# ----------------------------------------------------------------------------- crops
def _label(tile: np.ndarray, text: str) -> np.ndarray:
    bar = np.full((18, tile.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([bar, tile])


def triple(images: list[np.ndarray], names: list[str], y0: int, x0: int, size: int) -> np.ndarray:
    tiles = []
    for img, nm in zip(images, names):
        tiles.append(_label(to_u8(img[y0 : y0 + size, x0 : x0 + size]), nm))
        tiles.append(np.full((size + 18, 4, 3), 255, np.uint8))
    return np.concatenate(tiles[:-1], axis=1)


def sharpest_in(frames: list[np.ndarray], y0: int, x0: int, size: int) -> int:
    """The frame with the most Laplacian energy in a window (the one a viewer would pick)."""

    def energy(f):
        g = cv2.GaussianBlur(f[y0 : y0 + size, x0 : x0 + size].mean(axis=-1), (0, 0), 1.0)
        return float(np.mean(cv2.Laplacian(g, cv2.CV_32F) ** 2))

    return int(np.argmax([energy(f) for f in frames]))


def crop_windows(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, regions: np.ndarray, size: int
) -> tuple[tuple[int, int], list[tuple[int, int]]]:
    """Top-left corners of the most different window overall and in each region."""
    diff = np.abs(a.mean(axis=-1) - b.mean(axis=-1)) * valid
    score = cv2.boxFilter(diff, -1, (size, size), normalize=True, borderType=cv2.BORDER_CONSTANT)
    half = size // 2
    inner = np.zeros_like(valid)
    inner[half : -half or None, half : -half or None] = True
    inner &= cv2.erode(valid.astype(np.uint8), np.ones((size, size), np.uint8)) > 0

    def best(mask):
        s = np.where(mask, score, -1)
        cy, cx = np.unravel_index(int(np.argmax(s)), s.shape)
        return int(cy - half), int(cx - half)

    return best(inner), [
        best(inner & (regions == r)) if (inner & (regions == r)).any() else best(inner)
        for r in range(GRID * GRID)
    ]


# ----------------------------------------------------------------------------- one stack
def evaluate(
    name: str,
    pattern: str,
    result: Path,
    work: Path,
    out: Path,
    focus_stack: str | None = None,
    extra: dict[str, Path] | None = None,
) -> dict:
    """Scores, registration and crops of one stack; ``extra`` images (e.g. a ground truth)
    are registered and scored like the peers, and shown as a fourth crop."""
    t0 = time.perf_counter()
    side = json.loads(Path(str(result) + ".json").read_text())
    flex = read_srgb(result)
    shape = flex.shape[:2]
    # the frames as stored (IMREAD_UNCHANGED) are warped in their own geometry, then turned
    # as the result was (the sidecar's EXIF orientation)
    code = side.get("orientation", 1)
    stored = shape if code <= 4 else shape[::-1]
    frames, valid = [], np.ones(shape, bool)
    for meta, path in zip(side["frames"], side["inputs"]):
        f, cover = warp(read_srgb(Path(path)), np.array(meta["homography"]), stored)
        frames.append(upright(f, code))
        valid &= upright(cover, code)
    methods = {"flexdof": flex}
    registration = {}
    # peers are registered to a focus-selected composite of the aligned frames, not to the
    # result under test, so their placement does not depend on the method being judged
    composite = frames_composite(frames)
    peers = {
        "focus-stack": run_focus_stack(name, pattern, work, focus_stack),
        AS_SHOT_PEER: run_focus_stack(name, pattern, work, focus_stack, as_shot=True),
        "enfuse": run_enfuse(name, pattern, work),
        **(extra or {}),
    }
    unusable = {}
    for peer, path in peers.items():
        if path is None or not Path(path).exists():
            continue
        image = read_srgb(Path(path))
        h, cc = register(image, composite)
        if cc < USABLE_REGISTRATION:  # not the scene any more: neither scored nor covered
            unusable[peer] = cc
            continue
        warped, cover = warp(image, h, shape)
        methods[peer] = warped
        valid &= cover
        registration[peer] = cc
    ref = Reference(frames, valid)
    scores = {m: ref.measure(img) for m, img in methods.items()}
    scores["sharpest frame"] = ref.sharpest_frames()
    # what the frames' own pixels score: per pixel the frame with the most Laplacian energy
    # (a plain focus stacker)
    scores["frame composite"] = ref.measure(composite)
    scores = {m: {k: v.tolist() for k, v in s.items()} for m, s in scores.items()}
    paired = {
        peer: ref.paired_sharpness(flex, methods[peer]).tolist()
        for peer in ("focus-stack", AS_SHOT_PEER)
        if peer in methods
    }
    # PSNR (8-bit sRGB levels, common area) of every other image against each extra image
    fidelity = {
        k: {m: _psnr(img, methods[k], ref.valid) for m, img in methods.items() if m != k}
        for k in (extra or {})
        if k in methods
    }

    # crops: flexdof | focus-stack (as shot, or enfuse, where it gave no result; no peer
    # where none did) | the region's sharpest frame
    shown = [m for m in ("focus-stack", AS_SHOT_PEER, "enfuse") if m in methods][:1]
    peer = methods[shown[0]] if shown else flex
    corner, per_region = crop_windows(
        flex, peer, ref.valid, ref.regions, min(CROP_PX, shape[0] // GRID, shape[1] // GRID)
    )
    size = min(CROP_PX, shape[0] // GRID, shape[1] // GRID)
    more = [k for k in (extra or {}) if k in methods]
    peers_shown = [methods[m] for m in shown]
    best = sharpest_in(frames, *corner, size)
    cv2.imwrite(
        str(out / f"{name}_maxdiff.png"),
        triple(
            [flex, *peers_shown, frames[best], *(methods[k] for k in more)],
            ["flexdof", *shown, f"frame {best}", *more],
            *corner,
            size,
        )[..., ::-1],
        PNG,
    )
    rows = []
    for gr in range(GRID):
        row = []
        for gc in range(GRID):
            r = gr * GRID + gc
            y0, x0 = per_region[r]
            best = sharpest_in(frames, y0, x0, size)
            row.append(
                triple(
                    [flex, *peers_shown, frames[best], *(methods[k] for k in more)],
                    [
                        f"{REGION_NAMES[r]}: flexdof",
                        *shown,
                        f"sharpest frame here: {best}",
                        *more,
                    ],
                    y0,
                    x0,
                    size,
                )
            )
            row.append(np.full((row[-1].shape[0], 12, 3), 255, np.uint8))
        rows.append(np.concatenate(row[:-1], axis=1))
        rows.append(np.full((12, rows[-1].shape[1], 3), 255, np.uint8))
    cv2.imwrite(str(out / f"{name}_regions.png"), np.concatenate(rows[:-1])[..., ::-1], PNG)
    return {
        "result": str(result),
        "blur_span_px": side.get("kernel", {}).get("blur_span_px"),
        "registration_ecc": registration,
        "valid_fraction": float(ref.valid.mean()),
        "sharpest_frame_per_region": ref.sharpest.tolist(),
        "maxdiff_window": {"row": corner[0], "col": corner[1], "size": size},
        "region_windows": per_region,
        "scores": scores,
        "sharpness_paired": paired,
        "psnr_against": fidelity,
        "peer_failures": peer_failures(name, work),
        "unusable_peers": unusable,
        "seconds": time.perf_counter() - t0,
    }


# ----------------------------------------------------------------------------- report
def fmt(v: float, measure: str) -> str:
    if not np.isfinite(v):
        return "-"
    return f"{v:.3f}" if measure == "haze" else f"{v:.2f}"


def good_regions(
    scores: dict, against: str = "focus-stack", method: str = "flexdof"
) -> tuple[int, int]:
    """Regions where ``method`` is at least as good as ``against`` on every measure."""
    if against not in scores:
        return 0, 0
    ok = 0
    for r in range(GRID * GRID):
        verdicts = [
            at_least_as_good(m, scores[method][m][r], scores[against][m][r]) for m in MEASURES
        ]
        ok += all(v is not False for v in verdicts)
    return ok, GRID * GRID


def _haze_at_least_as_good(scores: dict, method: str) -> int:
    """Regions where ``method`` is at least as good as focus-stack on haze."""
    if method not in scores or "focus-stack" not in scores:
        return 0
    return sum(
        at_least_as_good("haze", scores[method]["haze"][r], scores["focus-stack"]["haze"][r])
        is not False
        for r in range(GRID * GRID)
    )


def report(results: dict, args) -> str:
    lines = [
        "# Real stacks, region by region (issue 13)",
        "",
        f"flexdof args: `{args.flexdof_args}`. All values in 8-bit sRGB display terms; "
        "lower is better for every measure. Verdict: flexdof against focus-stack "
        "(ties within " + ", ".join(f"{m} {a:g}/{r:.0%}" for m, (a, r) in TIES.items()) + ").",
        "",
        "| stack | blur span px | regions flexdof >= focus-stack on all 4 | "
        "... >= focus-stack as shot | ... >= enfuse | sharpness wins/ties/losses | halo | "
        "haze | noise | frame composite: haze >= focus-stack |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, res in results.items():
        s = res["scores"]
        counts = []
        for m in MEASURES:
            v = (
                [verdict(m, s["flexdof"][m][r], s["focus-stack"][m][r]) for r in range(9)]
                if "focus-stack" in s
                else []
            )
            counts.append(f"{v.count('win')}/{v.count('tie')}/{v.count('loss')}")
        a, n = good_regions(s)
        e, ne = good_regions(s, "enfuse")
        h, nh = good_regions(s, AS_SHOT_PEER)
        span = res["blur_span_px"]
        ceiling = _haze_at_least_as_good(s, "frame composite")
        lines.append(
            f"| {name} | {span:.1f} | **{a}/{n}** | {h}/{nh} | {e}/{ne} | "
            + " | ".join(counts)
            + f" | {ceiling}/{n} |"
        )
    for name, res in results.items():
        s = res["scores"]
        lines += [
            "",
            f"## {name}",
            "",
            f"Registration ECC: {res['registration_ecc']}; common area "
            f"{res['valid_fraction']:.0%}; sharpest frame per region "
            f"{res['sharpest_frame_per_region']}. Crops: `{name}_maxdiff.png`, "
            f"`{name}_regions.png`.",
            "",
        ]
        for peer, said in res.get("peer_failures", {}).items():
            lines += [f"{peer} gave no result: {said}", ""]
        for peer, cc in res.get("unusable_peers", {}).items():
            lines += [f"{peer}'s result does not register to the frames (ECC {cc:.2f}).", ""]
        methods = [
            m
            for m in (
                "flexdof",
                "multiframe",
                "focus-stack",
                AS_SHOT_PEER,
                "enfuse",
                "truth",
                "sharpest frame",
                "frame composite",
            )
            if m in s
        ]
        for m in MEASURES:
            lines += [
                f"**{m}** ({UNITS[m]})",
                "",
                "| region | " + " | ".join(methods) + " | flexdof vs focus-stack |",
                "|---" * (len(methods) + 2) + "|",
            ]
            for r in range(GRID * GRID):
                vals = [fmt(s[k][m][r], m) for k in methods]
                v = (
                    verdict(m, s["flexdof"][m][r], s["focus-stack"][m][r])
                    if "focus-stack" in s
                    else "-"
                )
                lines.append(f"| {REGION_NAMES[r]} | " + " | ".join(vals) + f" | {v} |")
            lines.append("")
        lines += paired_table(res.get("sharpness_paired", {}))
        a, n = good_regions(s)
        lines.append(
            f"flexdof at least as good as focus-stack on every measure in **{a}/{n}** regions."
        )
    return "\n".join(lines) + "\n"


def paired_table(paired: dict) -> list[str]:
    """The sharpness table paired on the same edges (``Reference.paired_sharpness``): per
    region and peer, flexdof's median width minus the peer's, and the shares of edges
    where flexdof is narrower / wider. A diagnostic beside the verdicts, which stay on the
    regions' medians."""
    if not paired:
        return []
    peers = list(paired)
    lines = [
        "**sharpness, paired on the same edges** (flexdof minus the peer, px; shares of the "
        "edges where flexdof is narrower / wider)",
        "",
        "| region | " + " | ".join(peers) + " |",
        "|---" * (len(peers) + 1) + "|",
    ]
    for r in range(GRID * GRID):
        cells = []
        for peer in peers:
            median, narrower, wider = paired[peer][r]
            cells.append("-" if not np.isfinite(median)
                         else f"{median:+.2f} ({narrower:.0%} / {wider:.0%})")
        lines.append(f"| {REGION_NAMES[r]} | " + " | ".join(cells) + " |")
    return [*lines, ""]


def output_folders(args) -> Path:
    """Make ``args.out`` and the work folder (``args.work``, default ``OUT/work``); return
    the work folder."""
    work = args.work or args.out / "work"
    work.mkdir(parents=True, exist_ok=True)
    args.out.mkdir(parents=True, exist_ok=True)
    return work


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stacks", default=",".join(STACKS))
    parser.add_argument("--flexdof-args", default="--threads 2")
    parser.add_argument(
        "--result",
        action="append",
        default=[],
        help="NAME=FILE: use an existing flexdof result (with FILE.json)",
    )
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parent / "results" / "real_regions"
    )
    parser.add_argument("--work", type=Path, help="flexdof/enfuse outputs (default OUT/work)")
    parser.add_argument(
        "--stack",
        action="append",
        default=[],
        metavar="NAME=GLOB",
        help="another stack: its frames, a glob relative to the shared data folder (e.g. "
        "pcb10a=focusstack-pcb/pcb10/pcb_00[0-5].JPG); list NAME in --stacks",
    )
    parser.add_argument(
        "--focus-stack",
        metavar="PATH",
        help="the focus-stack binary, for the peer result of stacks given with --stack and "
        "for its result with the frames' photometry as shot, on every stack (bash "
        "../shared/tools/build-focus-stack.sh prints it)",
    )
    args = parser.parse_args()
    stacks = {**STACKS, **dict(item.split("=", 1) for item in args.stack)}
    given = dict(item.split("=", 1) for item in args.result)
    work = output_folders(args)
    results = {}
    for name in args.stacks.split(","):
        if name not in stacks:
            raise SystemExit(f"unknown stack {name!r}; choose from {', '.join(stacks)}")
        result = (
            Path(given[name])
            if name in given
            else run_flexdof(name, stacks[name], work, shlex.split(args.flexdof_args))
        )
        results[name] = evaluate(name, stacks[name], result, work, args.out, args.focus_stack)
        a, n = good_regions(results[name]["scores"])
        print(
            f"{name}: flexdof >= focus-stack on every measure in {a}/{n} regions "
            f"({results[name]['seconds']:.0f} s)",
            flush=True,
        )
    (args.out / "real_regions.json").write_text(json.dumps(results, indent=1))
    (args.out / "real_regions.md").write_text(report(results, args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
