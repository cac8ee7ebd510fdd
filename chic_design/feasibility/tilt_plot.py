"""The plot of ``chic-design check --plot`` and of the build's report: max tilt against depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from chic_design.feasibility.records import FeasibilityReport
from chic_register.util.atomic import atomic_path


def save_tilt_plot(report: FeasibilityReport, png_path) -> Path:
    """Max tilt vs depth, coloured by limiting constraint, usable-depth bands at 0/15/30/45 deg.

    Written atomically (temporary file, then rename).
    """
    import matplotlib  # matplotlib, and its backend choice, only when a plot is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # (after the backend is chosen)

    path = Path(png_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    zs = np.array([t.depth_mm for t in report.tilt_limits])
    ts = np.array([t.max_tilt_deg for t in report.tilt_limits])
    labels = [t.limited_by if t.usable_at_zero_tilt else "unusable even at tilt 0"
              for t in report.tilt_limits]
    vis = [t.visibility_tilt_deg for t in report.tilt_limits]
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=120)
    try:
        ax.plot(zs, ts, color="0.6", lw=1, zorder=1)
        if all(v is not None for v in vis):
            ax.plot(zs, vis, color="0.3", lw=1, ls="--", zorder=1, label="visibility alone")
        cmap = plt.get_cmap("tab10")
        for k, lab in enumerate(dict.fromkeys(labels)):
            m = np.array([x == lab for x in labels])
            color = "0.5" if lab.startswith("unusable") else cmap(k % 10)
            ax.scatter(zs[m], ts[m], s=14, color=color, label=lab, zorder=2)
        for u in report.usable_depth:
            for a, b in u.ranges_mm:
                ax.plot([a, b], [u.tilt_deg, u.tilt_deg], color="k", lw=3, alpha=0.35,
                        solid_capstyle="butt")
            ax.axhline(u.tilt_deg, color="k", lw=0.5, ls=":")
            ax.text(zs[-1], u.tilt_deg + 0.8, f"{u.tilt_deg:g} deg: {u.total_mm:g} mm usable",
                    ha="right", va="bottom", fontsize=7)
        ax.set_xlabel("depth z along the axis (mm)")
        ax.set_ylabel("max tilt, worst azimuth (deg)")
        ax.set_title(f"{report.name}: max image tilt (pixel {report.pixel_size_mm:g} mm, "
                     f"slice {report.slice_thickness_mm:g} mm)", fontsize=9)
        ax.set_xlim(zs[0], zs[-1])
        ax.set_ylim(0, 90)
        ax.legend(fontsize=7, loc="upper left", title="limited by", title_fontsize=7, framealpha=0.9)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return path
