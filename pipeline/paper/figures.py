"""The paper's simulated figures: PSF profiles (Fig. 3), PSF dissimilarities (Fig. 5),
MTFs and the noise/DOF table (Fig. 9).

Cores return arrays and plain dicts; :func:`render_figures` writes PNG (matplotlib
Agg, no pyplot state), CSV and Markdown. The setup is Sec. 4.1's: Fujinon 12.5 mm
f/1.4 on the 1/3" 1024x768 CCD (4.65 um pixels), normal camera focused at 750 mm,
EDOF sweep ``p(0) = 12.5 mm``, ``s = 1 mm/s``, ``T = 0.36 s`` (focal plane from
infinity to 446.5 mm).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy import ndimage

from pipeline.core import colour as io
from pipeline.core import deconvolve, optics, psf, spectra
from pipeline.core.lens import Lens
from pipeline.core.motion import Profile, constant_speed
from pipeline.errors import InputError
from pipeline.io.profiles import load_lens

LENS = "fujinon-12.5mm-f1.4-sony-1-3in"
DEPTHS_MM = (450.0, 550.0, 750.0, 1100.0, 2000.0)
FOCUS_MM = 750.0
SWEEP = (12.5, 1.0, 0.36)  # p(0) mm, s mm/s, T s (Sec. 4.1)
POSITIONS_PX = (0.0, 128.0, 256.0, 384.0, 512.0)  # along the centre row, from the centre
F_NUMBERS = (1.4, 2.0, 2.8, 4.0, 5.6, 8.0)
SIGMAS = (0.001, 0.002, 0.005, 0.01)
COC_MM = 0.0141  # Sec. 4.3, for a 1/3" sensor
FIGURES = ("3", "5", "9")


def edof_profile(*, translation_scale: float = 1.0) -> Profile:
    """Sec. 4.1's sweep (k1), or one of ``translation_scale`` times its length about the
    same mid-point over the same exposure (k2 of Fig. 9a: ``translation_scale=0.5``)."""
    p0, speed, exposure = SWEEP
    mid = p0 + 0.5 * speed * exposure
    scaled = speed * translation_scale
    return constant_speed(mid - 0.5 * scaled * exposure, scaled, exposure)


def normal_profile(lens: Lens, focus_mm: float = FOCUS_MM) -> Profile:
    """A still detector focused at ``focus_mm`` over the same exposure."""
    return constant_speed(optics.image_distance(lens.focal_length_mm, focus_mm), 0.0, SWEEP[2])


def _swept_depths(lens: Lens, profile: Profile) -> tuple[float, float]:
    lo, hi = profile.range_mm
    return (
        float(optics.focus_distance(lens.focal_length_mm, hi)),
        float(optics.focus_distance(lens.focal_length_mm, lo)),
    )


# ----------------------------------------------------------------------------- Fig. 3
def fig3_profiles(
    lens: Lens,
    depths_mm: Sequence[float] = DEPTHS_MM,
    *,
    edof: Profile | None = None,
    focus_mm: float = FOCUS_MM,
    models: Sequence[str] = ("pillbox", "gaussian"),
    half_px: int = 30,
) -> dict[str, np.ndarray]:
    """Centre rows of the normal camera's PSFs and the EDOF camera's IPSFs (Fig. 3).

    Parameters
    ----------
    lens : Lens
    depths_mm : sequence of float
        Scene depths.
    edof : Profile, optional
        The EDOF motion; default Sec. 4.1's sweep.
    focus_mm : float
        Focus of the normal (still) camera, exposed as long as ``edof``.
    models : sequence of {"pillbox", "gaussian"}
    half_px : int
        Kernels are ``2 half_px + 1`` pixels wide.

    Returns
    -------
    dict
        ``"x_px"``: (2h+1,); ``"normal-<model>"``, ``"edof-<model>"``: (depths, 2h+1)
        centre rows of pixel-integrated kernels (Eqs. 3, 4; IPSFs from the closed
        forms of Eqs. 6, 7, integrated over pixels).
    """
    edof = edof or edof_profile()
    f = lens.focal_length_mm
    normal = constant_speed(optics.image_distance(f, focus_mm), 0.0, edof.exposure_s)
    size = 2 * half_px + 1
    out: dict[str, np.ndarray] = {"x_px": np.arange(-half_px, half_px + 1, dtype=np.float64)}
    for model in models:
        for name, profile in (("normal", normal), ("edof", edof)):
            rows = [
                psf.integrated_psf(lens, d, profile, model=model, size=size)[half_px]
                for d in depths_mm
            ]
            out[f"{name}-{model}"] = np.array(rows)
    return out


def _plot_profiles(data: dict, depths_mm: Sequence[float], path: Path, title: str) -> None:
    keys = [k for k in data if k != "x_px"]
    cols = 2
    fig = Figure(figsize=(10, 3.5 * math.ceil(len(keys) / cols)))
    for k, key in enumerate(keys):
        ax = fig.add_subplot(math.ceil(len(keys) / cols), cols, k + 1)
        for depth, row in zip(depths_mm, data[key]):
            ax.plot(data["x_px"], row, label=f"{depth:.0f} mm")
        ax.set_yscale("log")
        ax.set_ylim(1e-5, 1.5)
        kind, model = key.split("-")
        label = "normal camera PSF" if kind == "normal" else "EDOF camera IPSF"
        ax.set_title(f"({'abcdefgh'[k]}) {label}, {model}")
        ax.set_xlabel("pixel (centre row)")
        ax.set_ylabel("energy per pixel")
    fig.axes[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def psf_vs_ipsf_figure(
    lens: Lens, profile: Profile, path: str | Path, *, model: str | None = None
) -> Path:
    """PNG of normal-camera PSFs vs the IPSFs of ``profile`` at 5 depths (Fig. 3 style).

    The depths are those in focus at 10, 30, 50, 70 and 90 % of the swept image
    distances; the normal camera is focused at the middle one.
    """
    lo, hi = profile.range_mm
    if hi <= lo:
        raise InputError("the profile does not move: no swept depth range to plot")
    f = lens.focal_length_mm
    p = lo + (hi - lo) * np.array([0.9, 0.7, 0.5, 0.3, 0.1])
    depths = [float(optics.focus_distance(f, x)) for x in p]
    blur_px = lens.aperture_mm * (hi - lo) / lo / lens.pixel_pitch_mm  # Eq. 2, largest
    g = lens.gaussian_g if (model or lens.psf_model) == "gaussian" else 0.25
    half = min(math.ceil(2 * g * blur_px) + 2, psf.MAX_KERNEL_SIZE // 2)
    data = fig3_profiles(
        lens, depths, edof=profile, focus_mm=depths[2], models=(model or lens.psf_model,),
        half_px=half,
    )
    out = Path(path)
    _plot_profiles(data, depths, out, f"{lens.name}: {lo:.4f}-{hi:.4f} mm sweep")
    return out


# ----------------------------------------------------------------------------- Fig. 5
def shifted_ipsf(
    lens: Lens,
    depth_mm: float,
    profile: Profile,
    offset_px: float,
    *,
    size: int,
    supersample: int = 7,
    step_px: float = 0.1,
) -> np.ndarray:
    """IPSF of a point imaged ``offset_px`` right of the image centre, with magnification.

    A chief ray through the lens centre lands at ``x p(t) / v`` on a detector at
    ``p(t)`` (Sec. 3 footnote 1), with ``x = offset_px`` where the point is in focus
    (``p = v``); so the lens PSF (Eq. 3 pillbox) slides along the row while its blur
    changes. The kernel is the time average (Eq. 5) of pillboxes of diameter
    ``b(t)`` centred at ``x (p(t) - v) / v``, rasterised by :func:`pipeline.core.psf.raster_pillbox`
    on a ``supersample``-times finer grid (shifts rounded to ``1/supersample`` px)
    and binned to pixels; time steps are small enough that ``b`` and the shift
    change by at most ``step_px`` per step (midpoint rule). Centred on the in-focus
    position, odd ``size``, sums to 1.
    """
    if size < 1 or size % 2 == 0:
        raise InputError(f"size must be a positive odd integer, got {size!r}")
    if supersample < 1 or supersample % 2 == 0:
        raise InputError(f"supersample must be a positive odd integer, got {supersample!r}")
    v = optics.image_distance(lens.focal_length_mm, depth_mm)
    to_px = lens.aperture_mm / v / lens.pixel_pitch_mm  # Eq. 2 in pixels per mm of |v - p|
    fine_size = size * supersample
    centre = fine_size // 2
    fine = np.zeros((fine_size, fine_size))
    for duration, p_start, p_end in profile.segments():
        change = abs(p_end - p_start) * max(to_px, abs(offset_px) / v)
        n = max(1, math.ceil(change / step_px))
        for p in p_start + (np.arange(n) + 0.5) / n * (p_end - p_start):
            diameter = lens.blur_px(v, p) * supersample  # Eq. 2
            half = math.ceil(0.5 * diameter) + 1
            disk = psf.raster_pillbox(diameter, half) * (duration / n)  # Eq. 3
            shift = round(offset_px * (p - v) / v * supersample)
            top, left = centre - half, centre - half + shift
            if top < 0 or left < 0 or left + 2 * half + 1 > fine_size:
                raise InputError(
                    f"size={size} px is too small for the IPSF at offset {offset_px} px; "
                    "pass a larger size"
                )
            fine[top : top + 2 * half + 1, left : left + 2 * half + 1] += disk
    binned = fine.reshape(size, supersample, size, supersample).sum(axis=(1, 3))
    return binned / binned.sum()


def _matrix(kernels: Sequence[np.ndarray]) -> np.ndarray:
    n = len(kernels)
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1, n):
            out[i, j] = out[j, i] = spectra.dissimilarity(kernels[i], kernels[j])  # Eq. 8
    return out


def fig5_matrices(
    lens: Lens,
    depths_mm: Sequence[float] = DEPTHS_MM,
    positions_px: Sequence[float] = POSITIONS_PX,
    *,
    size: int = 81,
    supersample: int = 7,
) -> dict[str, np.ndarray]:
    """Pair-wise Eq. 8 dissimilarities (Fig. 5), pillbox model.

    ``"normal-depth"``: normal camera focused at 750 mm, 5 depths (Fig. 5a);
    ``"edof-depth"``: EDOF IPSFs at the centre pixel, 5 depths (5b);
    ``"edof-position"``: EDOF IPSFs at 5 positions along the centre row for a
    point at 750 mm, magnification included (:func:`shifted_ipsf`, 5c).
    """
    normal = normal_profile(lens)
    edof = edof_profile()
    normal_k = [psf.integrated_psf(lens, d, normal, model="pillbox", size=size) for d in depths_mm]
    edof_k = [psf.integrated_psf(lens, d, edof, model="pillbox", size=size) for d in depths_mm]
    position_k = [
        shifted_ipsf(lens, FOCUS_MM, edof, x, size=size, supersample=supersample)
        for x in positions_px
    ]
    return {
        "normal-depth": _matrix(normal_k),
        "edof-depth": _matrix(edof_k),
        "edof-position": _matrix(position_k),
    }


# ----------------------------------------------------------------------------- Fig. 9
def fig9_kernels(lens: Lens, *, depth_mm: float = FOCUS_MM, size: int = 81) -> dict:
    """k1 (Sec. 4.1's sweep) and k2 (half the translation, same mid-point), pillbox."""
    return {
        name: psf.integrated_psf(
            lens, depth_mm, edof_profile(translation_scale=scale), model="pillbox", size=size
        )
        for name, scale in (("k1", 1.0), ("k2", 0.5))
    }


def natural_image() -> np.ndarray:
    """skimage's ``camera`` (512x512, sRGB 8-bit) linearised to [0, 1] linear light."""
    from skimage import data

    return io.srgb_to_linear(data.camera().astype(np.float64) / 255.0)


def deconvolution_noise(
    image: np.ndarray, kernel: np.ndarray, sigma: float, *, seed: int = 0
) -> float:
    """Sec. 4.3's effective noise: std of ``I - wiener(k * I + n, k)``, n ~ N(0, sigma^2).

    The blur reflects the image at its borders (as the Wiener padding does); the
    statistic is taken inside a margin of the kernel radius.
    """
    rng = np.random.default_rng(seed)
    blurred = ndimage.convolve(image, kernel, mode="reflect")
    captured = blurred + rng.normal(0.0, sigma, image.shape)
    restored = deconvolve.wiener(captured, kernel, noise_sigma=sigma)
    m = kernel.shape[0] // 2
    return float(np.std((image - restored)[m:-m, m:-m]))


def fig9_table(
    lens: Lens,
    image: np.ndarray,
    *,
    sigmas: Sequence[float] = SIGMAS,
    f_numbers: Sequence[float] = F_NUMBERS,
    kernels: dict | None = None,
    seed: int = 0,
) -> list[dict]:
    """Effective noise and DOF of normal cameras vs EDOF k1, k2 (Fig. 9b).

    A normal camera at f/N collects ``(1.4/N)^2`` of the light in the same exposure;
    scaled up to the same brightness its noise is ``sigma (N/1.4)^2``. The EDOF
    cameras (f/1.4) have the Wiener deconvolution noise of
    :func:`deconvolution_noise`. DOF: :func:`pipeline.core.optics.depth_of_field` with a
    14.1 um circle of confusion at 750 mm; EDOF: the swept depth range.

    Returns
    -------
    list of dict
        One row per camera: ``camera``, ``noise`` (list per sigma), ``near_mm``, ``far_mm``.
    """
    base = min(f_numbers)
    rows = []
    for n in f_numbers:
        near, far = optics.depth_of_field(lens.focal_length_mm, n, FOCUS_MM, COC_MM)
        rows.append(
            {
                "camera": f"normal f/{n:g}",
                "noise": [s * (n / base) ** 2 for s in sigmas],
                "near_mm": near,
                "far_mm": far,
            }
        )
    kernels = kernels or fig9_kernels(lens)
    for name, scale in (("k1", 1.0), ("k2", 0.5)):
        near, far = _swept_depths(lens, edof_profile(translation_scale=scale))
        noise = [deconvolution_noise(image, kernels[name], s, seed=seed) for s in sigmas]
        rows.append({"camera": f"EDOF {name}", "noise": noise, "near_mm": near, "far_mm": far})
    return rows


def equivalent_f_number(noise: float, sigma: float, base_f_number: float = 1.4) -> float:
    """The f-number whose scaled normal-camera noise ``sigma (N/N0)^2`` equals ``noise``."""
    return base_f_number * math.sqrt(noise / sigma)


# ----------------------------------------------------------------------------- writing
def _fmt_mm(x: float) -> str:
    return "inf" if math.isinf(x) else f"{x:.1f}"


def _write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence]) -> None:
    with path.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)


def _markdown(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def _render_fig3(lens: Lens, out: Path) -> list[Path]:
    data = fig3_profiles(lens)
    png = out / "fig3_psf_profiles.png"
    _plot_profiles(data, DEPTHS_MM, png, "Fig. 3: normal camera focused at 750 mm vs EDOF sweep")
    rows = [
        [key, depth, *(f"{v:.6g}" for v in row)]
        for key in data
        if key != "x_px"
        for depth, row in zip(DEPTHS_MM, data[key])
    ]
    table = out / "fig3_psf_profiles.csv"
    _write_csv(table, ["kernel", "depth_mm", *(f"{x:g}" for x in data["x_px"])], rows)
    return [png, table]


def _render_fig5(lens: Lens, out: Path) -> list[Path]:
    mats = fig5_matrices(lens)
    labels = {
        "normal-depth": [f"{d:g}" for d in DEPTHS_MM],
        "edof-depth": [f"{d:g}" for d in DEPTHS_MM],
        "edof-position": [f"({x:g},0)" for x in POSITIONS_PX],
    }
    fig = Figure(figsize=(13, 4))
    vmax = max(m.max() for m in mats.values())
    md, rows = [], []
    for k, (key, m) in enumerate(mats.items()):
        ax = fig.add_subplot(1, 3, k + 1)
        im = ax.imshow(m, vmin=0, vmax=vmax, cmap="viridis")
        ax.set_xticks(range(5), labels[key], fontsize=7)
        ax.set_yticks(range(5), labels[key], fontsize=7)
        ax.set_title(f"({'abc'[k]}) {key}")
        fig.colorbar(im, ax=ax, fraction=0.046)
        md.append(f"### {key}\n\n" + _markdown([""] + labels[key], [
            [labels[key][i], *(f"{v:.4g}" for v in m[i])] for i in range(5)
        ]))
        rows += [[key, labels[key][i], *(f"{v:.6g}" for v in m[i])] for i in range(5)]
    fig.tight_layout()
    png = out / "fig5_dissimilarity.png"
    fig.savefig(png, dpi=100)
    table = out / "fig5_dissimilarity.csv"
    _write_csv(table, ["matrix", "row", "c0", "c1", "c2", "c3", "c4"], rows)
    text = out / "fig5_dissimilarity.md"
    text.write_text("# Fig. 5: Eq. 8 dissimilarities\n\n" + "\n".join(md), encoding="utf-8")
    return [png, table, text]


def _render_fig9(lens: Lens, out: Path) -> list[Path]:
    kernels = fig9_kernels(lens)
    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot(1, 1, 1)
    mtf_rows = []
    for name, color in (("k1", "red"), ("k2", "blue")):
        freq, mag = spectra.mtf(kernels[name])
        ax.plot(freq, mag, color=color, label=name)
        mtf_rows.append([name, *(f"{v:.6g}" for v in mag)])
    ax.set_xlabel("frequency (cycles/pixel)")
    ax.set_ylabel("MTF")
    ax.set_title("(a) MTFs of the EDOF IPSFs")
    ax.legend()
    fig.tight_layout()
    png = out / "fig9_mtf.png"
    fig.savefig(png, dpi=100)
    mtf_csv = out / "fig9_mtf.csv"
    _write_csv(mtf_csv, ["kernel", *(f"{f:.5g}" for f in freq)], mtf_rows)
    rows = fig9_table(lens, natural_image(), kernels=kernels)
    header = ["camera", *(f"sigma={s:g}" for s in SIGMAS), "DOF near mm", "DOF far mm"]
    body = [
        [r["camera"], *(f"{v:.4f}" for v in r["noise"]), _fmt_mm(r["near_mm"]),
         _fmt_mm(r["far_mm"])]
        for r in rows
    ]
    table = out / "fig9_table.csv"
    _write_csv(table, header, body)
    equiv = [
        [r["camera"], *(f"f/{equivalent_f_number(v, s):.2f}" for v, s in zip(r["noise"], SIGMAS))]
        for r in rows
        if r["camera"].startswith("EDOF")
    ]
    text = out / "fig9_table.md"
    text.write_text(
        "# Fig. 9b: effective noise and DOF (normal camera noise at f/1.4 = sigma)\n\n"
        + _markdown(header, body)
        + "\n## Normal-camera f-number with the same noise as the EDOF camera\n\n"
        + _markdown(["camera", *(f"sigma={s:g}" for s in SIGMAS)], equiv),
        encoding="utf-8",
    )
    return [png, mtf_csv, table, text]


def render_figures(out_dir: str | Path, *, which: Sequence[str] = FIGURES) -> list[Path]:
    """Write Figs. 3, 5 and 9 (PNG, CSV, Markdown) into ``out_dir``; return the paths."""
    unknown = [w for w in which if w not in FIGURES]
    if unknown:
        raise InputError(f"unknown figure(s) {unknown}; choose from {', '.join(FIGURES)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lens = load_lens(LENS)
    renderers = {"3": _render_fig3, "5": _render_fig5, "9": _render_fig9}
    written: list[Path] = []
    for key in which:
        written += renderers[key](lens, out)
    return written
