"""The ``flexdof`` command: sub-commands are discovered in :mod:`pipeline.commands`.

Building the parser imports argparse and the command modules only (each imports its
job inside ``run``), so ``flexdof --help`` never loads numpy, dask or OpenCV.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import logging
import os
import pkgutil
import sys
from importlib import import_module

from pipeline import __version__, commands
from pipeline.commands._flags import Parser
from pipeline.errors import FlexdofError


def build_parser() -> Parser:
    """The top-level parser with every sub-command of :mod:`pipeline.commands`."""
    parser = Parser(
        prog="flexdof",
        top=True,
        description="Flexible depth-of-field photography (Kuthirummal et al., TPAMI 2011).",
        epilog="Run `flexdof COMMAND --help` for a command's flags.",
    )
    parser.add_argument("--version", action="version", version=f"flexdof {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue  # helpers shared by commands (flags, progress display)
        import_module(f"{commands.__name__}.{info.name}").register(subparsers)
    return parser


def configure_logging(quiet: bool, verbose: bool) -> None:
    """Warnings and errors by default; ``-v`` adds flexdof's own events (INFO and DEBUG),
    not the libraries' (an EXIF reader's DEBUG is one line per tag); ``-q`` leaves errors
    only. tifffile's own warnings (an offset past the end of a file cut short) are left
    out: the reader reports the same fault as one error that names the file."""
    level = logging.ERROR if quiet else logging.DEBUG if verbose else logging.WARNING
    logging.basicConfig(format="%(levelname)s: %(message)s")  # no-op when already set up
    logging.getLogger().setLevel(max(level, logging.WARNING))
    logging.getLogger("pipeline").setLevel(level)
    logging.getLogger("tifffile").setLevel(logging.ERROR)


def subcommands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """Yield ``(command path, parser)`` for every sub-command below ``parser``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield (*path, name), sub
                yield from subcommands(sub, (*path, name))


HEAP_BUFFERS_MIB = 256  # see tune_process


def tune_process() -> None:
    """Process settings for the jobs, made before numpy loads (measured on pcb7/pcb10).

    * One BLAS thread: the only BLAS call (the blur-span fit's small ``np.dot``) left
      OpenBLAS threads spinning on the shared cores (pcb10: -0.6 s CPU of 4.8).
    * One glibc malloc arena (``M_ARENA_MAX`` 1): with an arena per dask thread, a
      frame buffer freed in one thread is not reused by another, and peak memory grows
      (pcb7: 389 -> 344 MiB).
    * Buffers up to ``HEAP_BUFFERS_MIB`` from that arena's heap, kept there when freed
      (``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD``): glibc otherwise maps each buffer
      above 32 MiB (a 3 Mpx float32 RGB frame is 36 MiB) fresh from the kernel and
      page-faults it in again, frame after frame: pcb10 spent 0.7-1.0 s of system CPU
      on that, 0.25-0.55 s without it, and 3.2 s instead of 3.5 s of wall time (median
      of 4 paired runs), peak memory unchanged (410-460 MiB). Forcing small buffers out
      to ``mmap`` instead (threshold 128 KiB) cost +0.6 s of system CPU on pcb7.
    * No transparent huge pages for numpy's buffers (``NUMPY_MADVISE_HUGEPAGE`` 0): numpy
      asks the kernel for huge pages on every large array, and where the kernel then
      compacts memory to find them on the first touch (``defrag`` ``madvise``, the
      default of Debian and Ubuntu), each of the guards' full-size temporaries costs a
      compaction: pcb7 spent 1.5-2.0 s of system CPU, 0.7-0.8 s without, and 4.0-4.2
      instead of 4.6-4.7 s of wall time (three paired runs); user CPU and peak memory
      the same. A numpy already imported is switched at once.
    Skipped where libc is not glibc.
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    numpy = sys.modules.get("numpy")
    core = getattr(numpy, "_core", None) or getattr(numpy, "core", None)  # numpy 2, 1.26
    switch = getattr(core, "multiarray", None)
    if switch is not None and hasattr(switch, "_set_madvise_hugepage"):
        switch._set_madvise_hugepage(os.environ["NUMPY_MADVISE_HUGEPAGE"] != "0")
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-8, 1)  # M_ARENA_MAX
        libc.mallopt(-3, HEAP_BUFFERS_MIB << 20)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, HEAP_BUFFERS_MIB << 20)  # M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        pass


# numpy submodules that numpy imports lazily and no job of the pipeline uses
UNUSED_NUMPY_SUBMODULES = frozenset(
    {"testing", "f2py", "ma", "ctypeslib", "rec", "char", "strings", "random"}
)


def import_scipy_lean() -> None:
    """Import ``scipy.fft`` and ``scipy.special`` without the numpy submodules they do not
    use (issue 15: about 60 ms, a twentieth of ``flexdof stack`` on a 7-frame stack).

    scipy's array-API layer (``scipy._lib.array_api_compat.numpy``, loaded by every scipy
    subpackage) clones numpy's namespace with ``from numpy import *`` and ``hasattr`` over
    ``dir(numpy)``; numpy lists its lazily loaded submodules in both ``__all__`` and
    ``__dir__``, so the clone imports ``numpy.testing``, ``numpy.f2py``, ``numpy.ma`` and
    others. While scipy loads, both leave out :data:`UNUSED_NUMPY_SUBMODULES` not yet
    imported; they stay importable and load on first use as before (``np.random`` in the
    simulator, for one). Only the clone's namespace lacks them: it is scipy's array-API
    view of numpy, whose standard has none of them. Does nothing where numpy has no
    ``__dir__`` of its own or scipy's layer is already loaded.
    """
    import numpy

    listed, exported = numpy.__dict__.get("__dir__"), numpy.__dict__.get("__all__")
    if listed is None or exported is None or "scipy._lib._array_api" in sys.modules:
        return

    def lean(names) -> list[str]:
        return [
            name
            for name in names
            if name not in UNUSED_NUMPY_SUBMODULES or f"numpy.{name}" in sys.modules
        ]

    numpy.__dir__, numpy.__all__ = (lambda: lean(listed())), lean(exported)
    try:
        from scipy import fft, special  # noqa: F401  (loaded here, used by the jobs)
    finally:
        numpy.__dir__, numpy.__all__ = listed, exported


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; user errors are printed as one line and give exit code 2."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.quiet and args.verbose:
        parser.error("-q/--quiet and -v/--verbose exclude each other")
    configure_logging(args.quiet, args.verbose)
    try:
        tune_process()
        import_scipy_lean()
        from pipeline.io.write import install_signal_cleanup  # imports numpy: not for --help

        install_signal_cleanup()  # SIGTERM (kill, systemctl stop) cleans up like Ctrl-C
        return int(args.func(args) or 0)
    except BrokenPipeError:  # output piped into e.g. `head`
        return 0
    except (FlexdofError, ValueError, OSError) as err:
        print(f"flexdof {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"flexdof {args.command}: interrupted", file=sys.stderr)
        return 130


def entry() -> None:
    """The ``flexdof`` console script: :func:`main`, with the garbage collector tuned for a
    process that imports much and then works on few, large objects (issue 15).

    The first generation is collected every 20000 net allocations instead of 700: the
    ~10^5 objects of the imports (numpy, scipy, dask, OpenCV) otherwise trigger ~130
    collections, 30 ms of ``flexdof stack``'s start-up; cycles are still collected
    (long ``workflow`` runs), only less often. At the end ``gc.freeze()`` moves every
    object still alive out of the collector's reach, so the interpreter's teardown frees
    them by reference counting alone instead of also traversing them (60 of its 85 ms
    on pcb7). Only for the console script: :func:`main` is also called in-process
    (tests, scripts).
    """
    gc.set_threshold(20_000, 10, 10)
    code = main()
    gc.freeze()
    sys.exit(code)


if __name__ == "__main__":
    entry()
