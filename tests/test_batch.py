"""Batch engine: one dask graph of stacks, local and on a real 2-worker dask.distributed cluster.

Stacks are downscaled copies of the real focal stacks in ../shared/data, plus
synthetic ones (a textured scene whose two halves come into focus at opposite
ends of the stack), plus the shipped sample ``stacks/motorcycle`` when present.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.errors import FlexdofError
from pipeline.io.read import read_frame
from pipeline.io.write import write_image
from pipeline.jobs.batch import BatchJob, run_batch
from pipeline.jobs.options import StackOptions

distributed = pytest.importorskip("distributed")

REAL_STACKS = {  # name: (folder in shared data, frame glob)
    "pcb7": ("focusstack-pcb/pcb7", "pcb_*.jpg"),
    "pcb10": ("focusstack-pcb/pcb10", "*.JPG"),
    "beetle": ("chimpstackr-beetle", "*.jpg"),
    "amber": ("shinestacker-amber", "*.jpg"),
}
ESTIMATED = {"pcb7", "synthetic-b"}  # stacks whose blur span the engine estimates


def copy_real_stack(source: Path, pattern: str, dest: Path, width: int = 384) -> Path:
    """Downscaled copy of a real stack's frames (JPEG, ``width`` px wide)."""
    dest.mkdir(parents=True)
    for file in sorted(source.glob(pattern)):
        image = cv2.imread(str(file))
        scale = width / image.shape[1]
        small = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        assert cv2.imwrite(str(dest / file.name), small)
    return dest


def make_synthetic_stack(
    dest: Path, *, seed: int, frames: int = 5, shape=(96, 128), ext: str = ".png"
) -> Path:
    """A textured scene, left half in focus in the first frame, right half in the last."""
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.0)
    texture = 0.1 + 0.8 * (texture - texture.min()) / np.ptp(texture)
    dest.mkdir(parents=True)
    half = shape[1] // 2
    for i in range(frames):
        frame = np.empty_like(texture)
        for sigma, cols in (
            (0.6 * i, slice(None, half)),
            (0.6 * (frames - 1 - i), slice(half, None)),
        ):
            blurred = cv2.GaussianBlur(texture, (0, 0), sigma) if sigma > 0 else texture
            frame[:, cols] = blurred[:, cols]
        write_image(dest / f"frame_{i:02d}{ext}", frame)
    return dest


def build_stacks(shared_data: Path, root: Path) -> dict[str, Path]:
    """Six+ stacks under ``root``: four real (downscaled) and two synthetic."""
    stacks = {
        name: copy_real_stack(shared_data / folder, pattern, root / name)
        for name, (folder, pattern) in REAL_STACKS.items()
    }
    stacks["synthetic-a"] = make_synthetic_stack(root / "synthetic-a", seed=1)
    stacks["synthetic-b"] = make_synthetic_stack(root / "synthetic-b", seed=2, ext=".tif")
    return stacks


def options_for(name: str) -> StackOptions:
    return StackOptions(blur_span_px=None if name in ESTIMATED else 6.0)


def jobs_for(stacks: dict[str, Path], out: Path) -> list[BatchJob]:
    out.mkdir(parents=True, exist_ok=True)
    return [
        BatchJob(
            name,
            (str(path),),
            str(out / f"{name}.tif"),
            StackOptions() if name == "motorcycle" else options_for(name),
        )
        for name, path in stacks.items()
    ]


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def sidecar_without_timings(output: Path) -> dict:
    data = json.loads(output.with_name(output.name + ".json").read_text())
    data.pop("timings_s")
    return data


def flatten(obj, prefix: str = "") -> dict:
    """Leaves of nested dicts/lists keyed by their path (for pytest.approx)."""
    if isinstance(obj, dict):
        return {
            k: v for key, item in obj.items() for k, v in flatten(item, f"{prefix}/{key}").items()
        }
    if isinstance(obj, list):
        return {
            k: v for i, item in enumerate(obj) for k, v in flatten(item, f"{prefix}/{i}").items()
        }
    return {prefix: obj}


@pytest.fixture(scope="module")
def stacks(shared_data, tmp_path_factory, repo_root) -> dict[str, Path]:
    found = build_stacks(shared_data, tmp_path_factory.mktemp("stacks"))
    motorcycle = repo_root / "stacks" / "motorcycle"
    if (motorcycle / "stack.toml").is_file():  # the shipped sample, once it is generated
        found["motorcycle"] = motorcycle
    return found


@pytest.fixture(scope="module")
def cluster():
    """Two worker processes on 127.0.0.1, spawned with this process's environment.

    dask's nanny otherwise sets OMP/OPENBLAS_NUM_THREADS=1 (BLAS sums in another
    order: last-bit differences in estimated blur spans) and MALLOC_TRIM_THRESHOLD_
    (2-3x slower numpy allocations); bit-identical results need like environments.
    """
    import dask

    with (
        dask.config.set({"distributed.nanny.pre-spawn-environ": {}}),
        distributed.LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
        ) as local_cluster,
    ):
        yield local_cluster


@pytest.fixture(scope="module")
def local_reference(stacks, tmp_path_factory) -> dict[str, Path]:
    """Every stack through the batch engine on the local scheduler."""
    out = tmp_path_factory.mktemp("local")
    seen: list[str] = []
    results = run_batch(
        jobs_for(stacks, out), concurrency=2, on_result=lambda r: seen.append(r["key"])
    )
    assert [r["status"] for r in results] == ["done"] * len(stacks), results
    assert sorted(seen) == sorted(stacks)  # one on_result per stack
    return {r["key"]: Path(r["output"]) for r in results}


def test_local_batch_matches_single_stack_job(local_reference, stacks, tmp_path):
    """The batch wrapper changes nothing: same bytes as process_stack run directly."""
    from pipeline.jobs.stack import process_stack
    from pipeline.parallel.scheduler import scheduler_context

    name = "synthetic-b"
    with scheduler_context(None, 1):
        process_stack(stacks[name], tmp_path / "direct.tif", options_for(name))
    assert sha256(tmp_path / "direct.tif") == sha256(local_reference[name])
    assert (
        sidecar_without_timings(tmp_path / "direct.tif")["kernel"]
        == sidecar_without_timings(local_reference[name])["kernel"]
    )


def test_distributed_batch_equals_local(cluster, stacks, local_reference, tmp_path):
    events: list[tuple] = []
    results = run_batch(
        jobs_for(stacks, tmp_path),
        scheduler=cluster.scheduler_address,
        on_progress=lambda *event: events.append(event),
    )
    assert [r["status"] for r in results] == ["done"] * len(stacks), results
    workers = {r["worker"] for r in results}
    assert len(workers) == 2, f"both workers should take stacks, got {workers}"
    assert os.getpid() not in {int(w.rsplit(":", 1)[1]) for w in workers}
    for r in results:
        output = Path(r["output"])
        assert sha256(output) == sha256(local_reference[r["key"]]) == r["output_sha256"]
        got = flatten(sidecar_without_timings(output))
        want = flatten(sidecar_without_timings(local_reference[r["key"]]))
        assert got.keys() == want.keys()
        for path, value in want.items():  # floats to the last bits of BLAS-order differences
            if isinstance(value, float):
                assert got[path] == pytest.approx(value, rel=1e-12, abs=1e-15), path
            else:
                assert got[path] == value, path
    # per-stack progress travelled back from the workers, for every stack
    assert {key for key, *_ in events} == set(stacks)
    assert {stage for _, stage, *_ in events} >= {"align", "accumulate", "deconvolve"}


def test_worker_killed_mid_run(cluster, stacks, local_reference, tmp_path):
    """SIGKILL a worker while it processes a stack: the batch still completes, correctly."""
    started = threading.Event()
    killed: dict = {}

    def killer() -> None:
        with distributed.Client(cluster.scheduler_address, set_as_default=False) as client:
            assert started.wait(60)
            pids = client.run(os.getpid)
            for _ in range(200):
                busy = {addr: keys for addr, keys in client.processing().items() if keys}
                if busy:
                    addr = sorted(busy)[0]
                    killed.update(pid=pids[addr], keys=busy[addr])
                    os.kill(pids[addr], signal.SIGKILL)
                    return
                started.wait(0.01)

    thread = threading.Thread(target=killer)
    thread.start()
    results = run_batch(
        jobs_for(stacks, tmp_path),
        scheduler=cluster.scheduler_address,
        concurrency=len(stacks),
        on_progress=lambda key, *rest: started.set(),
    )
    thread.join()
    assert killed, "no worker was busy: the test did not kill anything"
    assert [r["status"] for r in results] == ["done"] * len(stacks), results
    assert all(int(r["worker"].rsplit(":", 1)[1]) != killed["pid"] for r in results)
    for r in results:
        assert sha256(Path(r["output"])) == sha256(local_reference[r["key"]])


def test_one_bad_stack_fails_alone(stacks, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "frame_0.jpg").write_bytes(b"not a jpeg")
    jobs = [
        *jobs_for({"synthetic-a": stacks["synthetic-a"]}, tmp_path / "out"),
        BatchJob("bad", (str(bad),), str(tmp_path / "out" / "bad.tif")),
    ]
    results = run_batch(jobs, concurrency=2)
    assert [r["status"] for r in results] == ["done", "failed"]
    assert results[1]["error_kind"] == "input" and "frame_0.jpg" in results[1]["error"]
    assert not (tmp_path / "out" / "bad.tif").exists()
    image = read_frame(results[0]["output"])
    assert image.shape[:2] == (96, 128) and np.all(np.isfinite(image))


@pytest.mark.parametrize("kwargs", [{"concurrency": 0}, {"threads_per_stack": 0}])
def test_bad_arguments(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        run_batch([BatchJob("x", ("x",), "x.tif")], **kwargs)


def test_unreachable_scheduler(tmp_path):
    import dask

    with (
        dask.config.set({"distributed.comm.timeouts.connect": "1s"}),
        pytest.raises(FlexdofError, match="nothing listens on port 9"),
    ):
        run_batch([BatchJob("x", ("x",), str(tmp_path / "x.tif"))], scheduler="tcp://127.0.0.1:9")
