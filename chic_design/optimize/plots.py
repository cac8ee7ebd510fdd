"""The optimiser's plots: the Pareto set, and a design's precision map. Written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from chic_design.optimize.choose import LABELS
from chic_design.optimize.score import OBJECTIVES
from chic_register.util.atomic import save_figure


def _plt():
    import matplotlib  # matplotlib, and its backend choice, only when a plot is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # (after the backend is chosen)

    return plt


def save_pareto_plot(candidates, front, chosen: dict, baseline: dict | None, png_path) -> Path:
    """Three pairwise views of the objectives: every feasible candidate, the Pareto set, chosen, baseline."""
    plt = _plt()
    ok = [c for c in candidates if c["feasible"]]
    pairs = [(0, 1), (0, 2), (1, 2)]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), dpi=110)
    try:
        for ax, (i, j) in zip(axes, pairs):
            ki, kj = OBJECTIVES[i], OBJECTIVES[j]
            get = lambda rs, k: [r["objectives"][k] for r in rs]  # noqa: E731
            ax.scatter(get(ok, ki), get(ok, kj), s=8, color="0.75", label=f"feasible ({len(ok)})")
            ax.scatter(get(front, ki), get(front, kj), s=22, color="tab:blue", label=f"Pareto ({len(front)})")
            ax.scatter([chosen["objectives"][ki]], [chosen["objectives"][kj]], s=120, facecolors="none",
                       edgecolors="tab:red", linewidths=2, label="chosen")
            if baseline is not None and baseline.get("feasible"):
                ax.scatter([baseline["objectives"][ki]], [baseline["objectives"][kj]], marker="*", s=140,
                           color="k", label="baseline")
            ax.set_xlabel(f"{LABELS[ki][0]} ({LABELS[ki][1]})", fontsize=8)
            ax.set_ylabel(f"{LABELS[kj][0]} ({LABELS[kj][1]})", fontsize=8)
            ax.tick_params(labelsize=7)
        axes[0].legend(fontsize=7)
        fig.suptitle("Pareto set: size (min) vs usable tilt x depth region (max) vs predicted TRE (min)",
                     fontsize=9)
        fig.tight_layout()
    except BaseException:
        plt.close(fig)
        raise
    return save_figure(fig, png_path, dpi=fig.dpi)  # atomic, and closes the figure


def save_precision_map(pmap, tilt_limits, png_path, title: str) -> Path:
    """Worst-azimuth predicted TRE over depth x tilt; cells above the design's tilt limit are hatched out."""
    plt = _plt()
    depths = np.unique(pmap.column("depth_mm"))
    tilts = np.unique(pmap.column("tilt_deg"))
    grid = np.full((tilts.size, depths.size), np.nan)
    for r in pmap.rows:
        grid[np.searchsorted(tilts, r["tilt_deg"]), np.searchsorted(depths, r["depth_mm"])] = r["worst_tre_mm"]
    zs = np.array([t.depth_mm for t in tilt_limits])
    ts = np.array([t.max_tilt_deg if t.usable_at_zero_tilt else 0.0 for t in tilt_limits])
    limit = np.interp(depths, zs, ts)
    fig, ax = plt.subplots(figsize=(7.5, 4), dpi=120)
    try:
        shown = np.where(tilts[:, None] <= limit[None, :] + 1e-9, grid, np.nan)
        im = ax.imshow(shown, origin="lower", aspect="auto", cmap="viridis",
                       extent=(0, depths.size, 0, tilts.size))
        for a in range(tilts.size):
            for b in range(depths.size):
                v = grid[a, b]
                usable = tilts[a] <= limit[b] + 1e-9
                txt = f"{v:.2f}" if np.isfinite(v) and usable else "x"
                ax.text(b + 0.5, a + 0.5, txt, ha="center", va="center", fontsize=7,
                        color="w" if usable else "0.4")
        ax.set_xticks(np.arange(depths.size) + 0.5, [f"{d:g}" for d in depths], fontsize=7)
        ax.set_yticks(np.arange(tilts.size) + 0.5, [f"{t:g}" for t in tilts], fontsize=7)
        ax.set_xlabel("depth (mm)")
        ax.set_ylabel("tilt (deg)")
        fig.colorbar(im, ax=ax, label="predicted TRE, worst azimuth (mm)")
        ax.set_title(f"{title}\n(x: beyond the design's tilt limit)", fontsize=9)
        fig.tight_layout()
    except BaseException:
        plt.close(fig)
        raise
    return save_figure(fig, png_path, dpi=fig.dpi)  # atomic, and closes the figure
