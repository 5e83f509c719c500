"""The CLI's one flag vocabulary: every command builds its flags from these helpers.

argparse only (no numpy, no jobs): ``flexdof --help`` imports this module and nothing
heavy. The vocabulary (also the README's flag table):

- ``-o/--output`` for whatever a command writes (file or folder);
- ``--encoding {srgb16,linear16,float32,srgb8}`` for written images;
- ``--lens NAME|PATH``; depths in millimetres as ``--near-mm/--far-mm`` (a sweep or a
  depth range), ``--focus-mm``, ``--at-mm``, ``--depth-mm``; times in seconds as
  ``--exposure-s``; every quantity flag carries its unit;
- ``--align {estimate,analytic,none}`` (``--align-model``), ``--method {wiener,rl,multiframe}``;
- ``--threads``, ``--scheduler`` for where a job runs;
- ``--json`` on every command that produces a result;
- ``-q/--quiet`` and ``-v/--verbose`` anywhere on the line.

Old spellings (``--out``, ``--linear``, ``--float``, ``--near``, ``--far``, ``--exposure``,
``--depth`` of ``psf``, ``--sweep-mm``) still parse but are hidden from ``--help``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

# Mirrors of pipeline.jobs.options / pipeline.io.write (tests/test_cli_flags.py checks they
# agree): importing those modules would import numpy.
# The sparse prior is not offered on the command line: 100-160x Wiener's time for
# +0.06-0.09 dB (issue 13); the API, the accuracy benchmark and workflow files keep it.
# "multiframe" needs a focal stack's frames: not offered where one image is deconvolved.
CLI_METHODS = ("wiener", "rl", "multiframe")
SINGLE_IMAGE_METHODS = ("wiener", "rl")
ALIGN_MODES = ("estimate", "analytic", "none")
ALIGN_MODELS = ("auto", "similarity", "breathing", "keystone", "affine", "homography")
ENCODINGS = ("srgb16", "linear16", "float32", "srgb8")
DEFAULT_LENS = "fujinon-12.5mm-f1.4-sony-1-3in"

# Deprecated spellings: they parse, --help does not show them.
HIDDEN_ALIASES = {"--out", "--near", "--far", "--exposure", "--sweep-mm"}


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Show ``(default: X)`` when there is a default worth showing; hide deprecated aliases."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "%(default)" in text
            or "default:" in text
            or default is None
            or default is False
            or default is argparse.SUPPRESS
            or not action.option_strings
        ):
            return text
        return text + " (default: %(default)s)"

    def _format_action_invocation(self, action: argparse.Action) -> str:
        first, *rest = action.option_strings or [None]
        shown = [first, *(s for s in rest if s not in HIDDEN_ALIASES)]
        if first is None or len(shown) == len(action.option_strings):
            return super()._format_action_invocation(action)
        copy = argparse.Action(shown, action.dest, nargs=action.nargs, metavar=action.metavar)
        copy.choices = action.choices
        return super()._format_action_invocation(copy)


class Parser(argparse.ArgumentParser):
    """Every (sub)parser: the help formatter above and the global ``-q``/``-v`` flags.

    Sub-parsers inherit this class (argparse uses the parent's class), so ``-q`` and ``-v``
    are accepted before or after any sub-command. Their default is SUPPRESS below the top
    level, so a sub-parser does not reset a flag given before the sub-command.
    """

    def __init__(self, *args, top: bool = False, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)
        default = False if top else argparse.SUPPRESS
        group = self.add_argument_group("global flags (anywhere on the line)")
        verbosity = group.add_mutually_exclusive_group()
        verbosity.add_argument(
            "-q", "--quiet", action="store_true", default=default, help="only errors"
        )
        verbosity.add_argument(
            "-v",
            "--verbose",
            action="store_true",
            default=default,
            help="also normal events (clipped values, EXIF notes, estimates) and debug logs",
        )


def require_matplotlib(what: str) -> None:
    """Fail with a one-line install hint when the optional plotting library is missing."""
    import importlib.util

    from pipeline.errors import FlexdofError

    if importlib.util.find_spec("matplotlib") is None:
        raise FlexdofError(
            f"{what} draws with matplotlib, which is not installed: "
            "pip install 'flexdof[plots]' (or pip install matplotlib)"
        )


def add_json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--json", action="store_true", help="print a machine-readable summary (JSON) on stdout"
    )


def add_output(
    parser: argparse.ArgumentParser, help: str, *, required: bool = True, encoding: bool = False
) -> None:
    """``-o/--output`` (``--out`` is a hidden alias) and, for images, ``--encoding``."""
    parser.add_argument("-o", "--output", "--out", type=Path, required=required, help=help)
    if encoding:
        add_encoding(parser)


def add_encoding(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--encoding",
        choices=ENCODINGS,
        help="pixel encoding of a written image; srgb16 for .tif, srgb8 for .png/.jpg "
        "when omitted; linear16 and float32 are linear light (TIFF only)",
    )
    # old spellings of --encoding linear16 / float32
    parser.add_argument(
        "--linear", dest="encoding", action="store_const", const="linear16", help=argparse.SUPPRESS
    )
    parser.add_argument(
        "--float", dest="encoding", action="store_const", const="float32", help=argparse.SUPPRESS
    )


def add_lens(
    parser: argparse.ArgumentParser,
    help: str = "lens profile: a shipped name (e.g. fujinon-12.5mm-f1.4-sony-1-3in) or a "
    "TOML file",
    **kwargs,
) -> None:
    parser.add_argument("--lens", metavar="NAME|PATH", help=help, **kwargs)


def add_depth_range(
    parser: argparse.ArgumentParser,
    *,
    near: float | None = None,
    far: float | None = None,
    required: bool = False,
    what: str = "the sweep",
) -> None:
    """``--near-mm`` / ``--far-mm`` (old: ``--near`` / ``--far``)."""
    parser.add_argument(
        "--near-mm",
        "--near",
        type=float,
        default=near,
        required=required,
        metavar="MM",
        help=f"near end of {what}, mm",
    )
    parser.add_argument(
        "--far-mm",
        "--far",
        type=float,
        default=far,
        metavar="MM",
        help=f"far end of {what}, mm ('inf' allowed)",
    )


def add_exposure(parser: argparse.ArgumentParser, default: float, help: str) -> None:
    parser.add_argument(
        "--exposure-s", "--exposure", type=float, default=default, metavar="S", help=help
    )


def add_alignment(parser: argparse.ArgumentParser, *, defaults: bool = True) -> None:
    """The lens and the magnification compensation: flags of every job over a focal stack."""
    add_lens(
        parser,
        help="lens profile: a shipped name or a TOML file (default: the stack's stack.toml)",
    )
    parser.add_argument(
        "--align",
        choices=ALIGN_MODES,
        default="estimate" if defaults else None,
        help="magnification compensation: estimated homographies, the scaling predicted "
        "from the focus positions, or none",
    )
    parser.add_argument(
        "--align-model",
        choices=ALIGN_MODELS,
        default="similarity" if defaults else None,
        help="what an estimated alignment fits: a shift, turn and scaling (similarity: focus "
        "breathing, a rail, a steady hand; frames within 0.25 px of a breathing about the "
        "image centre get that breathing), the breathing alone (breathing: a camera that "
        "does not move), also the keystone of a wide-angle lens turned "
        "between frames (keystone), shear (affine) or all of these (homography); auto: the "
        "similarity, or the keystone where a pair of frames shows one (a depth gradient "
        "across the frame can look like one)",
    )


def add_compute(parser: argparse.ArgumentParser) -> None:
    """Where the job runs."""
    parser.add_argument(
        "--threads", type=int, help="local worker threads (default: one per core)"
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run on a dask.distributed cluster (tcp://host:port) instead of local threads",
    )


def add_method(
    parser: argparse.ArgumentParser, *, defaults: bool = True, methods=CLI_METHODS
) -> None:
    parser.add_argument(
        "--method",
        choices=methods,
        default="wiener" if defaults else None,
        help="deconvolution: Wiener or Richardson-Lucy"
        + (
            "; multiframe: the quality method, each depth restored from all frames "
            "(for stacks that follow the model; 2-8x slower, about 3x the memory)"
            if "multiframe" in methods
            else ""
        ),
    )
    parser.add_argument(
        "--tile-px",
        type=int,
        default=1024 if defaults else None,
        metavar="PX",
        help="side of the overlapping tiles large images are deconvolved in",
    )


def add_processing(parser: argparse.ArgumentParser, *, defaults: bool = True) -> None:
    """Flags of the commands that run the main job (stack, workflow run).

    ``defaults=False`` leaves every default ``None`` (workflow run: the file decides).
    """
    add_alignment(parser, defaults=defaults)
    add_method(parser, defaults=defaults)
    parser.add_argument(
        "--blur-span-px",
        type=float,
        metavar="PX",
        help="blur (px) of a point focused at one end of the stack seen at the other end "
        "(default: from the lens profile, else measured from the frames)",
    )
    parser.add_argument(
        "--white",
        type=float,
        metavar="LEVEL",
        help="the value of white in float TIFF frames in other units (e.g. 4095 for a "
        "12-bit sensor's counts; default: white in stack.toml, else 1)",
    )
    _switch(
        parser,
        "--frame-guard",
        "frame_guard",
        True,
        "for real photographs: keep the result within the aligned frames' range, take "
        "the sharpest frame where it shows more detail, hold the noise to a frame's and "
        "double a fitted blur span (slower; worse on stacks that follow the paper's model)",
    )
    _switch(
        parser,
        "--no-frame-range",
        "frame_range",
        False,
        "the paper's linear result as it is (by default, where every aligned frame is flat "
        "the result's fine band is taken from their average, the result is clipped to the "
        "frames' 3x3 range, and its noise held to a frame's where the Wiener filter's gain "
        "ceiling set its regularisation: no amplified noise in flat areas, no rims or dark moats)",
    )
    add_match_exposure(parser)
    add_crop(parser)
    parser.add_argument(
        "--max-pixels",
        type=int,
        metavar="N",
        help="refuse frames larger than this, before decoding them (default: 200000000)",
    )
    add_compute(parser)


def _switch(parser: argparse.ArgumentParser, flag: str, dest: str, value: bool, help: str):
    """A flag that sets ``dest`` to ``value``; left out, ``dest`` is ``None`` (the job's
    default, or a workflow file's)."""
    parser.add_argument(flag, dest=dest, action="store_const", const=value, help=help)


def add_crop(parser: argparse.ArgumentParser) -> None:
    """``--crop``: the result cropped to the area every aligned frame covers."""
    _switch(
        parser,
        "--crop",
        "crop",
        True,
        "crop the result to the area every aligned frame covers (frames moved between "
        "shots leave borders filled from their edges; by default the result keeps the "
        "reference frame's size and the sidecar's common_area says where that area is)",
    )


def add_match_exposure(parser: argparse.ArgumentParser) -> None:
    """``--match-exposure``: each frame divided by its own exposure."""
    _switch(
        parser,
        "--match-exposure",
        "match_exposure",
        True,
        "for frames shot at different exposures (a flash's output, flicker, a macro "
        "lens's effective aperture): divide each by its own, measured on the aligned frames "
        "(by default they are measured and reported only)",
    )


def stack_options(args: argparse.Namespace):
    """The job's :class:`~pipeline.jobs.options.StackOptions` from the parsed flags."""
    from pipeline.jobs.options import StackOptions

    defaults = StackOptions()

    def given(name: str):  # a flag the user gave (0 included), else the job's default
        value = getattr(args, name, None)
        return getattr(defaults, name) if value is None else value

    return StackOptions(
        lens=getattr(args, "lens", None),
        method=given("method"),
        align=given("align"),
        align_model=given("align_model"),
        encoding=getattr(args, "encoding", None),
        blur_span_px=getattr(args, "blur_span_px", None),
        tile_px=given("tile_px"),
        save_kernel=getattr(args, "save_kernel", None),
        max_pixels=given("max_pixels"),
        frame_guard=given("frame_guard"),
        frame_range=given("frame_range"),
        white=getattr(args, "white", None),
        match_exposure=given("match_exposure"),
        crop=given("crop"),
    )
