"""The accuracy benchmark's outputs: the CSV/Markdown table, the Pareto plot and the
summary of what to act on.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

from pipeline.errors import InputError
from pipeline.paper.bench.pareto import METRICS, Row, _groups, dominated_defaults, oriented

COLUMNS = (
    "group",
    "knob",
    "scene",
    "setting",
    "is_default",
    "metric",
    "value",
    "time_s",
    "requires",
    "note",
)


# ----------------------------------------------------------------------------- outputs
def write_table(rows: Sequence[Row], out: Path) -> None:
    """``accuracy.csv`` (all columns) and ``accuracy.md`` (a Markdown table)."""
    with open(out / "accuracy.csv", "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(COLUMNS)
        for r in rows:
            writer.writerow(
                [
                    r.group,
                    r.knob,
                    r.scene,
                    r.setting,
                    int(r.is_default),
                    r.metric,
                    f"{r.value:.6g}",
                    f"{r.time_s:.6g}",
                    r.requires,
                    r.note,
                ]
            )
    lines = [
        "| knob | scene | setting | default | metric | value | time s | requires |",
        "|---|---|---|---|---|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.knob} | {r.scene} | {r.setting} | {'**yes**' if r.is_default else ''} | "
            f"{r.metric} | {r.value:.4g} | {r.time_s:.3g} | {r.requires} |"
        )
    (out / "accuracy.md").write_text("\n".join(lines) + "\n", encoding="utf-8")


def read_table(path: Path) -> list[Row]:
    """Rows back from ``accuracy.csv``."""
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        if tuple(reader.fieldnames or ()) != COLUMNS:
            raise InputError(f"{path}: columns {reader.fieldnames}, expected {list(COLUMNS)}")
        return [
            Row(
                d["group"],
                d["knob"],
                d["scene"],
                d["setting"],
                bool(int(d["is_default"])),
                d["metric"],
                float(d["value"]),
                float(d["time_s"]),
                d["requires"],
                d["note"],
            )
            for d in reader
        ]


def write_plot(rows: Sequence[Row], path: Path) -> None:
    """Error vs time (log), one panel per (group, metric, scene), one curve per knob."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    panels = _groups(rows, ("group", "metric", "scene"))
    ncols = 3
    nrows = math.ceil(len(panels) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(6 * ncols, 4.2 * nrows), squeeze=False)
    for ax, ((group, metric, scene), panel) in zip(axes.ravel(), panels):
        for (knob,), curve in _groups(panel, ("knob",)):
            curve = sorted(curve, key=lambda r: r.time_s)
            t = [r.time_s for r in curve]
            v = [r.value for r in curve]
            (line,) = ax.plot(t, v, "o-", ms=4, lw=1, label=knob)
            for r in curve:
                ax.annotate(
                    r.setting,
                    (r.time_s, r.value),
                    fontsize=6,
                    alpha=0.7,
                    xytext=(3, 3),
                    textcoords="offset points",
                )
                if r.is_default:
                    ax.plot(
                        r.time_s,
                        r.value,
                        "*",
                        ms=14,
                        color=line.get_color(),
                        markeredgecolor="black",
                    )
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        if not METRICS[metric].higher_is_better and min(r.value for r in panel) > 0:
            ax.set_yscale("log")
        ax.set_title(f"{group}: {scene}", fontsize=9)
        ax.set_xlabel("time, s (best of repeats)")
        ax.set_ylabel(METRICS[metric].label, fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, loc="best")
    for ax in axes.ravel()[len(panels) :]:
        ax.axis("off")
    fig.suptitle("flexdof accuracy vs time (stars: defaults)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_summary(rows: Sequence[Row], path: Path, *, elapsed: float, quick: bool) -> None:
    """A few sentences a user can act on, from the measured numbers."""
    lines = [
        f"# Accuracy vs time ({'quick' if quick else 'full'} run, {elapsed:.0f} s)",
        "",
    ]
    lines += _highlights(rows)
    lines += ["", "## Defaults", ""]
    dominated = dominated_defaults(rows)
    conditional = [pair for pair in dominated_defaults(rows, conditional=True) if pair[1].requires]
    if not dominated:
        lines.append(
            "Every default is on the Pareto front: no measured setting is both >20% faster "
            "and clearly more accurate (margins in pipeline.paper.bench.pareto.METRICS)."
        )
    for d, r in dominated:
        lines.append(
            f"- DOMINATED: {d.knob} on {d.scene}: default {d.setting} ({_fmt(d)}, "
            f"{d.time_s:.3g} s) is beaten by {r.setting} ({_fmt(r)}, {r.time_s:.3g} s)."
        )
    for d, r in conditional:
        lines.append(
            f"- Where {r.requires} are known: {r.setting} beats the default {d.setting} on "
            f"{d.scene} ({_fmt(r)} in {r.time_s:.3g} s vs {_fmt(d)} in {d.time_s:.3g} s)."
        )
    lines += ["", "## Per knob (default vs the most accurate and the fastest setting)", ""]
    for (knob, scene, _metric), group in _groups(rows, ("knob", "scene", "metric")):
        defaults = [r for r in group if r.is_default]
        base = defaults[0] if defaults else min(group, key=lambda r: r.time_s)
        best = min(group, key=oriented)
        fast = min(group, key=lambda r: r.time_s)
        parts = [
            f"- **{knob}** ({scene}): {'default' if defaults else 'cheapest'} "
            f"{base.setting} = {_fmt(base)} in {base.time_s:.3g} s"
        ]
        if best is not base:
            parts.append(
                f"most accurate {best.setting} = {_fmt(best)} at "
                f"{best.time_s / base.time_s:.2g}x the time"
            )
        if fast is not base and fast is not best:
            parts.append(
                f"fastest {fast.setting} = {_fmt(fast)} at "
                f"{fast.time_s / base.time_s:.2g}x the time"
            )
        lines.append("; ".join(parts) + ".")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def _fmt(r: Row) -> str:
    return f"{r.value:.2f} dB" if r.metric == "psnr_db" else f"{r.metric} {r.value:.3g}"


def _find(rows, knob, setting_prefix, scene=None, metric=None):
    for r in rows:
        if (
            r.knob == knob
            and r.setting.startswith(setting_prefix)
            and (scene is None or r.scene == scene)
            and (metric is None or r.metric == metric)
        ):
            return r
    return None


def _highlights(rows: Sequence[Row]) -> list[str]:
    """Headline comparisons, each only if both of its rows were measured."""
    out = []
    scenes = sorted({r.scene for r in rows if r.group == "deconvolution"})
    for scene in scenes:
        w32 = _find(rows, "precision", "float32", scene)
        w64 = _find(rows, "precision", "float64", scene)
        wie = _find(rows, "method", "wiener", scene)
        spa = _find(rows, "method", "sparse", scene)
        rl = _find(rows, "method", "rl", scene)
        if w32 and w64:
            out.append(
                f"- {scene}: float64 deconvolution changes PSNR by {w64.value - w32.value:+.3f} "
                f"dB for {w64.time_s / w32.time_s:.2g}x the time of float32."
            )
        if wie and spa:
            out.append(
                f"- {scene}: sparse-prior deconvolution buys {spa.value - wie.value:+.2f} dB "
                f"over Wiener for {spa.time_s / wie.time_s:.2g}x the time"
                + (
                    f"; Richardson-Lucy {rl.value - wie.value:+.2f} dB for "
                    f"{rl.time_s / wie.time_s:.2g}x."
                    if rl
                    else "."
                )
            )
    for scene in sorted({r.scene for r in rows if r.knob == "alignment (final PSNR)"}):
        none = _find(rows, "alignment (final PSNR)", "none", scene)
        est = _find(rows, "alignment (final PSNR)", "estimate @768", scene)
        ana = _find(rows, "alignment (final PSNR)", "analytic", scene)
        if none and est:
            out.append(
                f"- {scene}: skipping alignment costs {est.value - none.value:.2f} dB; "
                f"estimating it adds {est.time_s - none.time_s:.2g} s to the run"
                + (
                    f"; the analytic scaling gives {ana.value - est.value:+.2f} dB vs "
                    f"estimated (needs absolute focus positions)."
                    if ana
                    else "."
                )
            )
    tol = [r for r in rows if r.knob == "layer tolerance"]
    d = next((r for r in tol if r.is_default), None)
    if d:
        for r in tol:
            if r is not d:
                out.append(
                    f"- simulation tolerance {r.setting}: render error {r.value:.2g} vs "
                    f"{d.value:.2g} at the default {d.setting}, "
                    f"{r.time_s / d.time_s:.2g}x the time."
                )
    for knob, off in (("occlusion", "off"), ("magnification", "off")):
        on, no = _find(rows, knob, "auto"), _find(rows, knob, off)
        if on and no:
            out.append(
                f"- simulation without {knob}: error {no.value:.2g} (vs {on.value:.2g}) for "
                f"{no.time_s / on.time_s:.2g}x the time."
            )
    counts = sorted(
        (r for r in rows if r.knob == "frames over 450-2000 mm" and r.metric == "psnr_db"),
        key=lambda r: int(r.setting.split()[0]),
    )
    if len(counts) >= 2:
        out.append(
            "- frames over the same range: PSNR "
            + ", ".join(f"{r.value:.2f} dB at {r.setting}" for r in counts)
            + f" (processing {counts[0].time_s:.2g} -> {counts[-1].time_s:.2g} s)."
        )
    theta = sorted(
        (r for r in rows if r.knob == "pixel-integration order (analytic)"),
        key=lambda r: r.time_s,
    )
    if theta:
        out.append(
            "- IPSF pixel integration: L1 error "
            + ", ".join(f"{r.value:.1e} at {r.setting}" for r in theta)
            + "."
        )
    return out
