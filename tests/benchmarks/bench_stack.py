"""Main-job benchmark (issue 3, 7): end-to-end time on a stack against decoding its frames alone.

    python tests/benchmarks/bench_stack.py [GLOB] [--repeat 3] [--profile]

Prints, from one run: decode-alone time (the frames read and converted to float32
linear light with the same 2-thread parallelism), the main job's stages (from its
sidecar: align, kernel, accumulate, deconvolve, write, total) and total / decode.
``--profile`` adds the top functions by cumulative time (cProfile). ``--memory``
measures peak memory (tracemalloc) for 8 vs 32 synthetic frames.
"""

from __future__ import annotations

import argparse
import cProfile
import glob
import io
import pstats
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import dask
import numpy as np

from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.jobs.options import StackOptions
from pipeline.jobs.stack import process_stack
from pipeline.parallel.scheduler import scheduler_context

DEFAULT = str(Path(__file__).resolve().parents[3] / "shared/data/focusstack-pcb/pcb7/pcb_*.jpg")


def decode_alone(files) -> float:
    t0 = time.perf_counter()
    dask.compute(*[dask.delayed(read_frame)(f) for f in files])
    return time.perf_counter() - t0


def run_job(files, out: Path, method: str) -> dict:
    result = process_stack(files, out, StackOptions(method=method))
    return result.sidecar["timings_s"]


def peak_memory(n_frames: int, folder: Path, shape=(1024, 1024, 3)) -> float:
    base = np.random.default_rng(0).random(shape, dtype=np.float32)
    for i in range(n_frames):
        write_image(
            folder / f"f_{i:03d}.tif", base * (0.5 + 0.5 * i / n_frames), encoding="float32"
        )
    tracemalloc.start()
    process_stack(
        [str(folder / "f_*.tif")],
        folder / "out.tif",
        StackOptions(align="none", blur_span_px=20.0, encoding="float32"),
    )
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("glob", nargs="?", default=DEFAULT)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--method", default="wiener")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--memory", action="store_true")
    args = parser.parse_args()
    files = sorted(glob.glob(args.glob))
    if not files:
        print(f"no files match {args.glob}", file=sys.stderr)
        return 2
    with scheduler_context(threads=2), tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.tif"
        decode = min(decode_alone(files) for _ in range(args.repeat))
        runs = [run_job(files, out, args.method) for _ in range(args.repeat)]
        best = min(runs, key=lambda r: r["total"])
        print(f"{len(files)} frames, {read_frame(files[0]).shape}, method {args.method}")
        print(f"decode alone (2 threads, best of {args.repeat}): {decode:.2f} s")
        for stage in ("align", "kernel", "accumulate", "deconvolve", "write", "total"):
            print(f"  {stage:<11} {best.get(stage, 0.0):6.2f} s")
        print(f"total / decode = {best['total'] / decode:.2f}")
        if args.profile:
            profiler = cProfile.Profile()
            profiler.enable()
            run_job(files, out, args.method)
            profiler.disable()
            text = io.StringIO()
            pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(15)
            print(text.getvalue())
        if args.memory:
            for n in (8, 32):
                folder = Path(tmp) / f"mem{n}"
                folder.mkdir()
                peak = peak_memory(n, folder)
                print(f"peak traced memory, {n} frames of 1024x1024x3: {peak:.0f} MiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
