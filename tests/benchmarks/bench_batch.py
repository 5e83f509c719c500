"""Batch throughput: stacks per minute, local vs a 1- and 2-worker dask.distributed cluster.

Run by hand (not in the test suite)::

    .venv/bin/python tests/benchmarks/bench_batch.py [--copies 3] [--width 512]

Builds a batch from downscaled copies of the real stacks in ../shared/data
(pcb7, pcb10, beetle, amber; ``--copies`` of each), then times the same batch
with :func:`pipeline.jobs.batch.run_batch` on

* the local threaded scheduler with 1 and 2 stacks in flight,
* a ``LocalCluster`` on 127.0.0.1 with 1 and 2 single-threaded worker processes,

and prints stacks/minute, the 2:1 ratios and the distributed scheduler's
overhead against the local one at equal parallelism. Every run's outputs are
checked byte-for-byte against the first.

dask's nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which turns
off glibc's adaptive mmap threshold: every large numpy temporary is then mmapped
and page-faulted afresh, and this pipeline runs 2-3x slower per stack. The
benchmark's clusters drop that variable (glibc's default) unless
``--dask-malloc-trim`` is given; start production workers the same way
(``DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON='{"OMP_NUM_THREADS": 1}'`` or
``dask worker --no-nanny``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "tests"))

import dask  # noqa: E402
import numpy as np  # noqa: E402
from distributed import LocalCluster  # noqa: E402
from test_batch import REAL_STACKS, copy_real_stack  # noqa: E402

from pipeline.io.read import read_frame  # noqa: E402
from pipeline.jobs.batch import BatchJob, run_batch  # noqa: E402
from pipeline.jobs.options import StackOptions  # noqa: E402


def build(root: Path, shared: Path, copies: int, width: int) -> list[tuple[str, Path]]:
    stacks = []
    for copy in range(copies):
        for name, (folder, pattern) in REAL_STACKS.items():
            key = f"{name}-{copy}"
            stacks.append((key, copy_real_stack(shared / folder, pattern, root / key, width)))
    return stacks


def timed(stacks, out: Path, **kwargs) -> tuple[float, dict]:
    out.mkdir()
    jobs = [
        BatchJob(key, (str(path),), str(out / f"{key}.tif"), StackOptions()) for key, path in stacks
    ]
    start = time.perf_counter()
    results = run_batch(jobs, **kwargs)
    seconds = time.perf_counter() - start
    bad = [r for r in results if r["status"] != "done"]
    if bad:
        raise SystemExit(f"failed stacks: {bad}")
    return seconds, {r["key"]: (r["output_sha256"], r["output"]) for r in results}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", type=int, default=3, help="copies of each real stack")
    parser.add_argument("--width", type=int, default=512, help="frame width after downscaling")
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument(
        "--dask-malloc-trim", action="store_true", help="keep dask's MALLOC_TRIM_THRESHOLD_"
    )
    args = parser.parse_args()
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
    if not args.dask_malloc_trim:
        environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        stacks = build(root / "stacks", args.shared, args.copies, args.width)
        n = len(stacks)
        print(f"{n} stacks, frames {args.width} px wide, blur span estimated from the frames")
        rows, reference = {}, None

        def record(label: str, seconds: float, hashes: dict) -> None:
            nonlocal reference
            reference = reference or hashes
            differ = [key for key in hashes if hashes[key][0] != reference[key][0]]
            worst = max(
                (
                    float(np.abs(read_frame(hashes[k][1]) - read_frame(reference[k][1])).max())
                    for k in differ
                ),
                default=0.0,
            )
            same = "yes" if not differ else f"{len(differ)} differ, max |diff| {worst:.2g}"
            rows[label] = seconds
            print(
                f"{label:<28} {seconds:7.1f} s  {60 * n / seconds:6.1f} stacks/min  "
                f"outputs identical: {same}"
            )

        for slots in (1, 2):
            record(
                f"local, {slots} in flight",
                *timed(stacks, root / f"local{slots}", concurrency=slots, threads_per_stack=1),
            )
        for workers in (1, 2):
            with (
                dask.config.set({"distributed.nanny.pre-spawn-environ": environ}),
                LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    host="127.0.0.1",
                    dashboard_address=None,
                ) as cluster,
            ):
                record(
                    f"distributed, {workers} worker(s)",
                    *timed(stacks, root / f"dist{workers}", scheduler=cluster.scheduler_address),
                )
        for kind in ("local", "distributed"):
            one = rows[f"{kind}, 1 in flight" if kind == "local" else f"{kind}, 1 worker(s)"]
            two = rows[f"{kind}, 2 in flight" if kind == "local" else f"{kind}, 2 worker(s)"]
            print(f"{kind}: 2-vs-1 throughput ratio {one / two:.2f}")
        for slots in (1, 2):
            local = rows[f"local, {slots} in flight"]
            dist = rows[f"distributed, {slots} worker(s)"]
            print(
                f"distributed overhead at {slots}: {dist - local:+.1f} s "
                f"({100 * (dist / local - 1):+.0f}%, {(dist - local) / n * 1000:+.0f} ms/stack)"
            )


if __name__ == "__main__":
    main()
