"""The hand mutants of issue 11, each applied to a scratch copy and run against the test
that must kill it (not collected by pytest; run from the repository root)::

    python tests/mutation/issue11_mutants.py            # all
    python tests/mutation/issue11_mutants.py wiener-k   # by name

Prints KILLED / SURVIVED per mutant; exit status 1 if any survived.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

# name: (file, original text, mutated text, tests that must kill it)
MUTANTS = {
    "wiener-k-not-conj": (
        "pipeline/core/deconvolve/wiener.py",
        "return np.conj(k_fft), base.astype(d2.dtype, copy=False), reg",
        "return k_fft, base.astype(d2.dtype, copy=False), reg",
        ["tests/test_deconvolve_asymmetric.py::test_methods_undo_a_one_sided_blur_and_the_flip_does_not"],
    ),
    "rl-k-not-adjoint": (
        "pipeline/core/deconvolve/common.py",
        "            np.conj(self.k_fft) * sfft.rfft2(x, workers=_WORKERS), s=self.shape,",
        "            self.k_fft * sfft.rfft2(x, workers=_WORKERS), s=self.shape,",
        ["tests/test_deconvolve_asymmetric.py::test_methods_undo_a_one_sided_blur_and_the_flip_does_not"],
    ),
    "admm-k-not-adjoint": (
        "pipeline/core/deconvolve/sparse.py",
        "k_conj = np.conj(dom.k_fft)",
        "k_conj = dom.k_fft",
        ["tests/test_deconvolve_asymmetric.py::test_methods_undo_a_one_sided_blur_and_the_flip_does_not"],
    ),
    "eq8-one-over-w": (
        "pipeline/core/spectra.py",
        "power = 1.0 / w2",
        "power = 1.0 / np.sqrt(w2)",
        ["tests/test_deconvolve_asymmetric.py::test_eq8_weights_fall_as_one_over_frequency_squared"],
    ),
    "tiles-ignore-censored": (
        "pipeline/parallel/tiling.py",
        "return dc.restore(y, p, mask[..., 0] if mask.ndim == 3 else mask)",
        "return dc.restore(y, p)",
        ["tests/test_deconvolve_asymmetric.py::test_tiles_honour_the_censored_mask"],
    ),
    "wiener-noise-term-halved": (
        "pipeline/core/deconvolve/wiener.py",
        "s2 = (energy - 4.0 * sigma**2)",
        "s2 = (energy - 2.0 * sigma**2)",
        ["tests/test_deconvolve_asymmetric.py::test_wiener_prior_fit_subtracts_the_whole_noise_term"],
    ),
    "align-chain-ignored": (
        "pipeline/core/align.py",
        "                if chain:\n                    anchor = i",
        "                if False:\n                    anchor = i",
        ["tests/test_issue11_kills.py::test_chained_alignment_matches_neighbours"],
    ),
    "align-perspective-check-off": (
        "pipeline/core/align.py",
        "    if np.max(np.abs(w - 1.0)) > _MAX_PERSPECTIVE:",
        "    if False:",
        ["tests/test_issue11_kills.py::test_strong_perspective_is_implausible"],
    ),
    "ledger-failures-ok": (
        "pipeline/workflow/ledger.py",
        'status = "failed" if failed else "ok"',
        'status = "ok"',
        ["tests/test_issue11_kills.py::test_a_run_with_failures_is_recorded_failed"],
    ),
    "hash-cache-size-only": (
        "pipeline/workflow/ledger.py",
        'if row is not None and (row["size"], row["mtime_ns"], row["inode"]) == key:',
        'if row is not None and row["size"] == key[0]:',
        ["tests/test_issue11_kills.py::test_hash_cache_sees_a_same_size_edit"],
    ),
    "deleted-sidecar-no-rerun": (
        "pipeline/workflow/run.py",
        "if not (output.is_file() and sidecar.is_file()):",
        "if not output.is_file():",
        ["tests/test_issue11_kills.py::test_a_deleted_sidecar_triggers_a_rerun"],
    ),
    "focus-at-infinity-rejected": (
        "pipeline/core/optics.py",
        "    if np.any(v < f):",
        "    if np.any(v <= f):",
        ["tests/test_optics_boundaries.py::test_image_distance_equal_to_f_is_focus_at_infinity"],
    ),
    "dof-near-branch-threshold": (
        "pipeline/core/optics.py",
        "near = focal_length_mm if coc_mm >= a else",
        "near = focal_length_mm if coc_mm >= 0.5 * a else",
        ["tests/test_optics_boundaries.py::test_dof_near_limit_on_both_sides_of_its_branch"],
    ),
    "no-exponential-backoff": (
        "pipeline/tether/session.py",
        "            self.sleep(delay)\n            delay = min(2 * delay, self.max_backoff_s)\n"
        "        if check:",
        "            self.sleep(delay)\n        if check:",
        ["tests/test_issue11_kills.py::test_busy_retries_back_off_exponentially_to_the_cap"],
    ),
    "read-noise-halved": (
        "pipeline/core/simulate/render.py",
        "rng.normal(0.0, exposure.read_noise_e, image.shape)",
        "rng.normal(0.0, 0.5 * exposure.read_noise_e, image.shape)",
        ["tests/test_noise_model.py"],
    ),
    "ipsf-tiny-change": (
        "pipeline/core/psf.py",
        "closed = (b_hi - b_lo) >= SMALL_CHANGE_PX",
        "closed = (b_hi - b_lo) > 1e-9 * np.maximum(b_hi, 1.0)",
        [
            "tests/test_psf.py::test_kernels_are_valid_and_analytic_equals_numeric",
            "tests/test_issue11_kills.py::test_tiny_blur_change_matches_quadrature_and_still_kernel",
        ],
    ),
}


def run(name: str) -> bool:
    path, old, new, tests = MUTANTS[name]
    with tempfile.TemporaryDirectory(prefix="flexdof-mutant-") as tmp:
        work = Path(tmp)
        for item in ("pipeline", "tests", "pyproject.toml", "lens_profiles", "stacks"):
            src = ROOT / item
            if src.is_dir():
                shutil.copytree(src, work / item, ignore=shutil.ignore_patterns("__pycache__"))
            elif src.exists():
                shutil.copy2(src, work / item)
        target = work / path
        text = target.read_text()
        if text.count(old) != 1:
            print(f"{name:30s} NOT APPLIED (original text found {text.count(old)} times)")
            return False
        target.write_text(text.replace(old, new))
        cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
        proc = subprocess.run(cmd, cwd=work, capture_output=True, text=True, check=False)
    killed = proc.returncode == 1  # tests failed (2-5: interrupted, usage, nothing collected)
    print(f"{name:30s} {'KILLED' if killed else 'SURVIVED'}  by {' '.join(tests)}")
    return killed


if __name__ == "__main__":
    names = sys.argv[1:] or list(MUTANTS)
    results = [run(n) for n in names]
    sys.exit(0 if all(results) else 1)
