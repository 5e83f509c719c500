"""The `flexdof optics` and `flexdof psf` commands: output formats and one-line errors."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.core import optics, psf
from pipeline.core.motion import constant_speed
from pipeline.io.profiles import load_lens
from pipeline.io.read import read_frame


def test_optics_prints_fig2_and_strict_json(capsys):
    assert main(["optics"]) == 0
    text = capsys.readouterr().out
    assert "158.2 um" in text and "320.5 um" in text and "512.8 um" in text
    assert main(["optics", "--near", "500", "--far", "inf", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)  # strict: no bare Infinity
    row = data["rows"][0]
    assert row["far_mm"] == "inf"
    assert row["translation_um"] == pytest.approx(
        optics.sweep_translation(12.5, 500, math.inf) * 1e3
    )


def test_psf_writes_the_kernel_and_the_fig3_plot(tmp_path, capsys):
    npy, tif, png = tmp_path / "k.npy", tmp_path / "k.tif", tmp_path / "fig3.png"
    assert main(["psf", "--depth", "900", "-o", str(npy), "--plot", str(png)]) == 0
    assert main(["psf", "--depth", "900", "-o", str(tif), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out.split("\n", 1)[1])
    lens = load_lens("fujinon-12.5mm-f1.4-sony-1-3in")
    expected = psf.integrated_psf(lens, 900.0, constant_speed(12.5, 0.36 / 0.36, 0.36))
    kernel = np.load(npy)
    assert kernel.shape == expected.shape == (summary["size"], summary["size"])
    assert np.allclose(kernel, expected, atol=1e-6)
    assert np.allclose(read_frame(tif), kernel, atol=1e-7)
    assert png.stat().st_size > 10_000


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["psf", "--depth", "10"], "focal length"),
        (["psf", "--exposure", "0"], "exposure"),
        (["psf", "-o", "kernel.bmp"], ".npy or .tif"),
        (["optics", "--near-mm", "500"], "--near-mm and --far-mm"),
        (["optics", "--near", "500"], "--near-mm and --far-mm"),  # old spelling
        (["optics", "--lens", "no-such-lens"], "no-such-lens"),
    ],
)
def test_bad_arguments_give_one_line_errors(tmp_path, monkeypatch, capsys, args, needle):
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err, err
    assert not list(tmp_path.iterdir())


def test_version(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and "flexdof" in capsys.readouterr().out


def test_zero_threads_is_named(repo_root, tmp_path, capsys):
    sample = str(repo_root / "stacks" / "motorcycle")
    assert main(["stack", sample, "-o", str(tmp_path / "x.tif"), "--threads", "0"]) == 2
    assert "--threads" in capsys.readouterr().err


def test_verbose_shows_flexdof_debug_but_not_the_libraries():
    """-v once printed the EXIF reader's DEBUG, one line per tag of every frame."""
    import logging

    from pipeline.cli import configure_logging

    saved = logging.getLogger().level, logging.getLogger("pipeline").level
    try:
        configure_logging(quiet=False, verbose=True)
        assert logging.getLogger("pipeline.io.exif").isEnabledFor(logging.DEBUG)
        assert not logging.getLogger("exifread").isEnabledFor(logging.INFO)
        assert logging.getLogger("exifread").isEnabledFor(logging.WARNING)
        configure_logging(quiet=True, verbose=False)
        assert not logging.getLogger("pipeline.jobs").isEnabledFor(logging.WARNING)
    finally:
        logging.getLogger().setLevel(saved[0])
        logging.getLogger("pipeline").setLevel(saved[1])


def test_scipy_is_imported_without_numpys_unused_submodules():
    """A fresh interpreter: scipy.fft works after the lean import, numpy's unused lazy
    submodules were not loaded by it, and numpy's ``__all__``/``dir`` are as before (the
    submodules still load on first use)."""
    code = """
import sys, numpy
before_all, before_dir = list(numpy.__all__), sorted(dir(numpy))
from pipeline.cli import import_scipy_lean, UNUSED_NUMPY_SUBMODULES
import_scipy_lean()
import scipy.fft, scipy.special
loaded = sorted(n for n in ('testing', 'f2py', 'ma', 'ctypeslib') if 'numpy.' + n in sys.modules)
assert loaded == [], loaded
assert numpy.__all__ == before_all and sorted(dir(numpy)) == before_dir
x = numpy.array([1.0, 2.0, 0.5, -1.0])
assert numpy.allclose(scipy.fft.irfft(scipy.fft.rfft(x), n=4), x)
assert abs(scipy.special.erf(0.5) - 0.5204998778130465) < 1e-15
assert numpy.ma.masked_array([1, 2], mask=[0, 1]).sum() == 1
print('ok')
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False)
    assert done.stdout.strip() == "ok", done.stderr


@pytest.mark.parametrize(
    ("setting", "numpy_first", "huge"),
    [(None, False, False), (None, True, False), ("1", False, True), ("1", True, True)],
)
def test_tune_process_turns_numpys_huge_pages_off_unless_asked_for(setting, numpy_first, huge):
    """numpy's huge-page requests are off after ``tune_process`` (each full-size temporary
    otherwise costs the kernel a compaction: pcb7's system CPU 1.5-2.0 s against 0.7-0.8), also
    for a numpy imported before it; a user's own ``NUMPY_MADVISE_HUGEPAGE=1`` stands. Read
    back through numpy's own switch, which returns the setting it replaces."""
    code = (
        ("import numpy\n" if numpy_first else "")
        + "from pipeline import cli\ncli.tune_process()\nimport numpy\n"
        + "print(numpy._core.multiarray._set_madvise_hugepage(True))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if setting is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = setting
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert out == [str(huge)]
