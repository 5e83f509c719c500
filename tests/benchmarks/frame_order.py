"""The real stacks given with their frames named out of focus order: region counts.

    python tests/benchmarks/frame_order.py [--stacks pcb7,beetle] [--baseline CHECKOUT] \
        [--out results/real_regions/frame_order.md]

Each real stack's frames are linked into a folder under new names (``img_00.jpg`` ...) in
three orders: as named (focus order), shuffled (seed 0) and rotated by half the stack (a
camera counter that wrapped: ``IMG_9998``, ``IMG_9999``, ``IMG_0001``). ``flexdof stack
FOLDER`` runs on each (and, with ``--baseline``, the same command from another checkout of
flexdof, e.g. ``git archive`` of an older commit, run with its ``pipeline`` on
``PYTHONPATH``), and the result is scored region by region against focus-stack as in
``real_stack_regions.py`` (focus-stack's results from the shared data; enfuse's made once
per stack, in ``--peers``). Columns: the regions
at least as good as focus-stack on all four measures, whether the job put the frames back in
focus order (its sidecar's inputs), and its time.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_stack_regions import evaluate, good_regions
from real_stacks import SHARED, STACKS


def orders(n: int) -> dict[str, list[int]]:
    return {
        "named in order": list(range(n)),
        "shuffled": np.random.default_rng(0).permutation(n).tolist(),
        "counter wrapped": [*range(n // 2, n), *range(n // 2)],
    }


def run(folder: Path, out: Path, checkout: Path | None) -> float:
    env = dict(os.environ)
    if checkout is not None:
        env["PYTHONPATH"] = str(checkout)
    cmd = [sys.executable, "-m", "pipeline.cli", "stack", str(folder), "-o", str(out)]
    t0 = time.perf_counter()
    subprocess.run([*cmd, "--threads", "2"], check=True, env=env, cwd=out.parent,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def in_focus_order(result: Path, files: list[str]) -> bool:
    used = [Path(p).resolve() for p in json.loads(Path(f"{result}.json").read_text())["inputs"]]
    truth = [Path(f).resolve() for f in files]
    return used in (truth, truth[::-1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stacks", default=",".join(STACKS))
    parser.add_argument("--baseline", type=Path, help="another checkout of flexdof to compare")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--peers", type=Path, help="cache of enfuse's results (default: temporary)")
    args = parser.parse_args()
    checkouts = {"this checkout": None}
    if args.baseline:
        checkouts["baseline"] = args.baseline.resolve()
    lines = [
        "| stack | frames named | " + " | ".join(
            f"{c}: regions / in focus order / s" for c in checkouts) + " |",
        "|---|---|" + "---|" * len(checkouts),
    ]
    with tempfile.TemporaryDirectory() as tmp:
        peers = args.peers or Path(tmp) / "peers"
        peers.mkdir(parents=True, exist_ok=True)
        for name in args.stacks.split(","):
            pattern = STACKS[name]
            files = sorted(glob.glob(str(SHARED / pattern)))
            for label, order in orders(len(files)).items():
                folder = Path(tmp) / f"{name}_{label.replace(' ', '_')}"
                folder.mkdir()
                for k, i in enumerate(order):
                    os.symlink(files[i], folder / f"img_{k:02d}{Path(files[i]).suffix}")
                cells = []
                for checkout_label, checkout in checkouts.items():
                    work = Path(tmp) / f"{folder.name}_{checkout_label.replace(' ', '_')}"
                    work.mkdir()
                    result = work / "result.tif"
                    seconds = run(folder, result, checkout)
                    scores = evaluate(name, pattern, result, peers, work)["scores"]
                    good, total = good_regions(scores)
                    kept = "yes" if in_focus_order(result, files) else "no"
                    cells.append(f"{good}/{total} / {kept} / {seconds:.1f}")
                lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
                print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
