"""``flexdof figures``: the paper's simulated Figs. 3, 5 and 9 as PNG, CSV and Markdown, and
its four applications (Figs. 6, 10, 11, 12) rendered on synthetic scenes, with numbers."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from pipeline.commands import _flags

SIMULATED = ("3", "5", "9")
APPLICATIONS = ("6", "10", "11", "12")
PNG_NAMES = {
    "6": "fig6_edof.png",
    "10": "fig10_discontinuous.png",
    "11": "fig11_tilted.png",
    "12": "fig12_nonplanar.png",
}


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "figures",
        help="reproduce the paper's simulated figures (Figs. 3, 5, 9) and applications "
        "(Figs. 6, 10, 11, 12)",
        description="Write Fig. 3 (PSF vs IPSF profiles), Fig. 5 (Eq. 8 dissimilarity "
        "matrices) and Fig. 9 (MTFs of k1, k2 and the table of effective noise and DOF, "
        "by Wiener deconvolution of a natural image) into --out. With --applications (or "
        "--only 6/10/11/12): render the four applications -- extended (Fig. 6), "
        "discontinuous (Fig. 10), tilted (Fig. 11) and non-planar (Fig. 12) DOF -- on "
        "synthetic scenes, as PNG panels plus applications.md with the measurements. "
        "Needs the 'plots' extra (pip install 'flexdof[plots]').",
    )
    _flags.add_output(parser, "output folder (created)")
    parser.add_argument(
        "--only",
        action="append",
        choices=SIMULATED + APPLICATIONS,
        help="figure to make (repeatable); default: 3, 5 and 9",
    )
    parser.add_argument(
        "--applications",
        action="store_true",
        help="also render the four applications (Figs. 6, 10, 11, 12)",
    )
    _flags.add_json(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    _flags.require_matplotlib("flexdof figures")
    from pipeline.commands import print_json
    from pipeline.paper import figures

    which = list(args.only or ([] if args.applications else figures.FIGURES))
    if args.applications:
        which += [a for a in APPLICATIONS if a not in which]
    simulated = [w for w in which if w in SIMULATED]
    written = figures.render_figures(args.output, which=simulated) if simulated else []
    apps = [w for w in which if w in APPLICATIONS]
    if apps:
        written += write_applications(args.output, apps)
    if args.json:
        print_json({"figures": which, "written": [str(p) for p in written]})
    elif not args.quiet:
        for path in written:
            print(path)
    return 0


def write_applications(out_dir: Path, which) -> list[Path]:
    """Render the applications in ``which``; write one PNG each and ``applications.md``."""
    from pipeline.paper import applications

    builders = {
        "6": applications.edof_application,
        "10": applications.discontinuous_application,
        "11": applications.tilted_application,
        "12": applications.nonplanar_application,
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written, sections = [], []
    for key in which:
        start = time.perf_counter()
        app = builders[key]()
        seconds = time.perf_counter() - start
        png = out / PNG_NAMES[key]
        _panels_png(app, png)
        written.append(png)
        sections.append(_markdown(app, png.name, seconds))
    text = out / "applications.md"
    text.write_text(
        "# The paper's applications on synthetic scenes\n\n"
        "`detail` is `pipeline.paper.applications.detail_transfer`: the band-passed image "
        "regressed on the sharp scene's band (after sub-pixel registration), 1 = as sharp "
        "as the scene, 0 = no detail. `noise` is the RMS of (noisy - noise-free) render.\n\n"
        + "\n".join(sections),
        encoding="utf-8",
    )
    written.append(text)
    return written


def _panels_png(app, path: Path) -> None:
    import numpy as np
    from matplotlib.figure import Figure

    from pipeline.core.colour import linear_to_srgb

    n = len(app.panels)
    rows, cols = next(iter(app.panels.values())).shape[:2]
    width = 4.2
    fig = Figure(figsize=(width * n, width * rows / cols + 0.6))
    for k, (label, image) in enumerate(app.panels.items()):
        ax = fig.add_subplot(1, n, k + 1)
        shown = linear_to_srgb(np.clip(np.asarray(image, np.float32), 0, 1))  # display only
        ax.imshow(shown, interpolation="nearest")
        ax.set_title(label, fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"Fig. {app.figure} analogue: {app.title}", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def _fmt(value) -> str:
    if isinstance(value, float):
        return "inf" if math.isinf(value) else f"{value:.3g}"
    if isinstance(value, (tuple, list)):
        return "(" + ", ".join(_fmt(v) for v in value) + ")"
    return str(value)


def _markdown(app, png_name: str, seconds: float) -> str:
    header = list(app.rows[0])
    lines = [
        f"## Fig. {app.figure}: {app.title}",
        "",
        f"![{app.title}]({png_name})  (rendered in {seconds:.1f} s)",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]
    lines += ["| " + " | ".join(_fmt(r[h]) for h in header) + " |" for r in app.rows]
    lines += ["", "| summary | value |", "|---|---|"]
    lines += [f"| {k} | {_fmt(v)} |" for k, v in app.summary.items()]
    return "\n".join(lines) + "\n"
