"""Overlay figures of a registration, like the paper's Fig. 5 and 6.

For each slice: the image as read, then the same image with every detected
candidate blob (the view spans all of them, rejected ones included), the fitted ellipse of tube centres, the model's predicted
tube crossings and the tube labels of the matched blobs. Written with
matplotlib's Agg backend, atomically (temporary file, then rename).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from chic_register.errors import ChicRegisterError
from chic_register.util.atomic import save_figure


def _pixels_of_ellipse(ell, spacing) -> np.ndarray:
    """Ellipse outline in (row, col) pixels; shape (n, 2)."""
    xy = ell.points(240)
    return np.stack([xy[:, 1] / spacing[0], xy[:, 0] / spacing[1]], axis=1)


def view_bounds(candidates_rc, shape, margin_px: float = 20.0):
    """(lo, hi) (row, col) of the zoomed view: every candidate blob, matched or rejected, with a margin.

    Zooming on the matched tubes alone hid the extra blobs the solver
    rejected, which is what a user wants to see when it refuses (issue 10).
    """
    rc = np.asarray(candidates_rc, dtype=float).reshape(-1, 2)
    top = np.array(shape[:2], dtype=float) - 1.0
    if not rc.shape[0]:
        return np.zeros(2), top
    return np.maximum(rc.min(axis=0) - margin_px, 0.0), np.minimum(rc.max(axis=0) + margin_px, top)


def draw_overlay(path, slices, registration=None, blobs=None, title: str | None = None) -> Path:
    """Write a PNG overlay of ``slices`` (list of Slice) to ``path``.

    ``registration``: a :class:`~chic_register.pipeline.register.Registration` (labels,
    ellipse, predictions); without it (no lock) only ``blobs`` (a list of
    :class:`~chic_register.detect.blobs.Blobs`, one per slice) are drawn.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ChicRegisterError(f"--overlay {path}: the overlay is a PNG file (give a name ending in .png)")
    n = len(slices)
    fig, axes = plt.subplots(n, 2, figsize=(9, 4.5 * n), squeeze=False)
    for j, sl in enumerate(slices):
        img = np.asarray(sl.pixels, dtype=float)
        res = registration.slices[j] if registration is not None else None
        rc = res.blobs_rc if res is not None else (blobs[j].centres_rc if blobs is not None else np.zeros((0, 2)))
        lo, hi = view_bounds(rc, img.shape)
        for ax in axes[j]:
            ax.imshow(img, cmap="gray", interpolation="nearest")
            ax.set_xlim(lo[1], hi[1])
            ax.set_ylim(hi[0], lo[0])
            ax.set_xticks([])
            ax.set_yticks([])
        axes[j, 0].set_title(f"{Path(sl.source).name}", fontsize=9)
        ax = axes[j, 1]
        if rc.shape[0]:
            ax.plot(rc[:, 1], rc[:, 0], "o", mfc="none", mec="yellow", ms=9, mew=1.0, label="candidates")
        if res is not None:
            if res.ellipse is not None:
                e = _pixels_of_ellipse(res.ellipse, sl.pixel_spacing_mm)
                ax.plot(e[:, 1], e[:, 0], "-", color="deepskyblue", lw=0.8, label="ellipse fit")
            pred = np.array(list(res.predicted_rc.values())) if res.predicted_rc else np.zeros((0, 2))
            if pred.size:
                ax.plot(pred[:, 1], pred[:, 0], "+", color="red", ms=8, mew=1.0, label="model crossings")
            for tid, bi in res.assignment.items():
                r, c = rc[bi]
                ax.annotate(tid, (c, r), xytext=(6, -6), textcoords="offset points", color="lime", fontsize=8)
            ax.set_title(f"depth {res.depth_mm:.2f} mm  tilt {res.tilt_deg:.2f}  twist {res.twist_deg:.2f} deg"
                         f"  rms {res.residual_rms_mm:.3f} mm", fontsize=8)
        else:
            ax.set_title(title or "no lock: candidates only", fontsize=9)
        ax.legend(loc="lower right", fontsize=7, framealpha=0.6)
    fig.tight_layout()
    save_figure(fig, path)
    return path
