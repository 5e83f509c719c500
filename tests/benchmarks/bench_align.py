"""Time alignment against decoding on a real focal stack (pcb10: 10 JPEG frames, 2048x1536).

Usage: .venv/bin/python tests/benchmarks/bench_align.py [STACK_DIR] [--max-side-px N] [--model M]

Prints, per frame: JPEG decode + sRGB linearisation, estimation (reduction + ECC), one
full-resolution RGB warp, and the recovered magnifications.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.align import estimate_alignment, warp

DEFAULT = Path(__file__).resolve().parents[3] / "shared" / "data" / "focusstack-pcb" / "pcb10"


def decode(path: Path) -> np.ndarray:
    """8-bit sRGB JPEG -> float32 linear RGB (gamma 2.2 approximation; not pipeline.io)."""
    rgb = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    lut = ((np.arange(256, dtype=np.float32) / 255) ** 2.2).astype(np.float32)
    return lut[rgb]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stack", nargs="?", type=Path, default=DEFAULT)
    parser.add_argument("--max-side-px", type=int, default=768)
    parser.add_argument("--model", default="similarity")
    args = parser.parse_args()
    files = sorted(p for p in args.stack.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
    n = len(files)

    t = time.perf_counter()
    frames = [decode(f) for f in files]
    t_decode = (time.perf_counter() - t) / n

    t = time.perf_counter()
    al = estimate_alignment(frames, model=args.model, max_side_px=args.max_side_px)
    t_est = (time.perf_counter() - t) / n

    t = time.perf_counter()
    for f, a in zip(frames, al):
        warp(f, a.homography, f.shape)
    t_warp = (time.perf_counter() - t) / n

    shape = frames[0].shape
    print(f"{args.stack.name}: {n} frames {shape}, max_side_px={args.max_side_px}, {args.model}")
    print(f"  decode+linearise {t_decode * 1e3:7.1f} ms/frame")
    print(f"  estimate         {t_est * 1e3:7.1f} ms/frame")
    print(f"  warp (RGB)       {t_warp * 1e3:7.1f} ms/frame")
    print("  magnification    " + " ".join(f"{a.scale:.4f}" for a in al))
    print("  methods          " + " ".join(a.method for a in al))


if __name__ == "__main__":
    main()
