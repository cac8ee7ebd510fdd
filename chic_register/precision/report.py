"""Text table, Markdown table and plot of a precision map (:func:`chic_register.precision.crlb.precision_map`)."""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

from chic_register.precision.crlb import PrecisionMap, Protocol, precision_map
from chic_register.util.atomic import save_figure

#: (column, heading, format) of the tables.
_COLUMNS = (("depth_mm", "depth mm", "{:.1f}"), ("tilt_deg", "tilt deg", "{:.0f}"),
            ("sd_normal_deg", "normal deg", "{:.3f}"), ("sd_twist_deg", "twist deg", "{:.4f}"),
            ("sd_depth_mm", "depth SD mm", "{:.4f}"), ("tre_mm", "TRE mm", "{:.4f}"),
            ("worst_tre_mm", "worst TRE mm", "{:.4f}"))


def describe(pm: PrecisionMap) -> str:
    """One line saying what the numbers are."""
    p = pm.protocol
    slices = f"{p.n_slices} slices {p.slice_spacing_mm:g} mm apart" if p.n_slices > 1 else "1 slice"
    return (f"Cramer-Rao bound, {slices}, {p.slice_thickness_mm:g} mm thick, {p.pixel_size_mm:g} mm pixels, "
            f"{p.noise} SNR {p.snr:g}, fluid gain unknown; RMS over {len(pm.azimuths_deg)} azimuths "
            f"(worst TRE: maximum), twist 0; TRE at ({', '.join(f'{v:g}' for v in pm.target_F_mm)}) mm in F")


def _cell(fmt: str, v: float) -> str:
    return fmt.format(v) if math.isfinite(v) else "-"


def format_map(pm: PrecisionMap, name: str = "") -> str:
    """A plain-text table, one row per (depth, tilt)."""
    head = [h for _, h, _ in _COLUMNS]
    rows = [[_cell(f, r[c]) for c, _, f in _COLUMNS] for r in pm.rows]
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    lines = [f"{name + ': ' if name else ''}{describe(pm)}",
             "  ".join(h.rjust(w) for h, w in zip(head, widths))]
    lines += ["  ".join(v.rjust(w) for v, w in zip(r, widths)) for r in rows]
    return "\n".join(lines)


def markdown_map(pm: PrecisionMap) -> str:
    """A Markdown table (for reports)."""
    head = [h for _, h, _ in _COLUMNS]
    lines = [describe(pm) + ".", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(_cell(f, r[c]) for c, _, f in _COLUMNS) + " |" for r in pm.rows]
    return "\n".join(lines)


def plot_map(pm: PrecisionMap, path, title: str = "") -> Path:
    """Normal angle, twist, depth and TRE bounds against depth, one line per tilt (PNG, written atomically)."""
    import matplotlib  # deferred: loads matplotlib only when used (one-shot start-up)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # deferred: loads matplotlib only when used (one-shot start-up)

    depth = pm.column("depth_mm")
    tilt = pm.column("tilt_deg")
    fig, axes = plt.subplots(2, 2, figsize=(9, 6.5), sharex=True)
    panels = (("sd_normal_deg", "normal angle (deg, RMS)"), ("sd_twist_deg", "twist SD (deg)"),
              ("sd_depth_mm", "depth SD (mm)"), ("tre_mm", "TRE at target (mm, RMS)"))
    for ax, (col, label) in zip(axes.ravel(), panels):
        vals = pm.column(col)
        for t in np.unique(tilt):
            m = tilt == t
            ax.plot(depth[m], vals[m], "o-", ms=3, label=f"tilt {t:g} deg")
        ax.set_ylabel(label)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("depth (mm)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{title + ': ' if title else ''}precision bound (CRLB)\n" + "\n".join(textwrap.wrap(describe(pm), 120)), fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    return Path(path)


#: The coarse map a design report shows: 5 depths x 3 tilts x 2 azimuths (about 4 s of one core).
DESIGN_TILTS_DEG = (0.0, 15.0, 30.0)


def design_precision(geometry, pixel_size_mm: float, slice_thickness_mm: float, snr: float = 20.0, *,
                     tilts_deg=DESIGN_TILTS_DEG, n_azimuths: int = 2, depth_fractions=(0.1, 0.3, 0.5, 0.7, 0.9)):
    """The coarse precision map of a design for its imaging protocol (one slice, Rician noise); None when
    the protocol has ideal (0 mm) pixels, for which no noise model applies."""
    if not pixel_size_mm > 0:
        return None
    L = float(geometry.body.length)
    return precision_map(geometry, Protocol(pixel_size_mm, slice_thickness_mm, snr),
                         [f * L for f in depth_fractions], tilts_deg, n_azimuths=n_azimuths)


def report_section(pm: PrecisionMap | None, plot_name: str | None = "precision.png") -> str:
    """The report's "Precision" section (Markdown)."""
    out = ["## Precision (Cramer-Rao bound)", ""]
    if pm is None:
        return "\n".join(out + ["Not computed: the imaging protocol has ideal (0 mm) pixels.", ""])
    out += ["The best precision any unbiased registration can reach from one slice of this design, "
            "from the pixels themselves (`chic-register precision` computes it for any protocol; "
            "the solver reports each pose's own covariance).", "", markdown_map(pm), ""]
    if plot_name:
        out += [f"![precision map]({plot_name})", ""]
    return "\n".join(out)
