"""Overlay figures of a registration (solve --overlay), like the paper's Fig. 5 and 6, readable at a glance.

For each slice two panels: the whole image as read, with a box around the
zoomed region (every candidate blob, even one far from the fiducial, is
seen there); and the zoomed region (the fiducial's blobs plus a margin) with
every candidate blob, the fitted ellipse of tube centres, the model's
predicted crossings, the tube labels of the matched blobs (placed apart from
each other and from the blobs, with a leader line when pushed aside) and a
scale bar in mm. Without a registration (no lock) the zoom spans every
candidate. Written with matplotlib's Agg backend, atomically.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np

from chic_register.errors import ChicRegisterError
from chic_register.util.atomic import save_figure

LABEL_GID = "tube label"
SCALE_BAR_GID = "scale bar"
SCALE_BAR_LABEL_GID = "scale bar label"
ZOOM_BOX_GID = "zoom box"
#: scale-bar lengths (mm) to choose from: the longest that fits a quarter of the view
SCALE_BAR_MM = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0)
DEFAULT_TUBE_RADIUS_MM = 1.5


def _pixels_of_ellipse(ell, spacing) -> np.ndarray:
    """Ellipse outline in (row, col) pixels; shape (n, 2)."""
    xy = ell.points(240)
    return np.stack([xy[:, 1] / spacing[0], xy[:, 0] / spacing[1]], axis=1)


def view_bounds(points_rc, shape, margin_px: float = 20.0):
    """(lo, hi) (row, col) of a view spanning ``points_rc`` with a margin, clipped to the image.

    No points: the whole image.
    """
    rc = np.asarray(points_rc, dtype=float).reshape(-1, 2)
    top = np.array(shape[:2], dtype=float) - 1.0
    if not rc.shape[0]:
        return np.zeros(2), top
    return np.maximum(rc.min(axis=0) - margin_px, 0.0), np.minimum(rc.max(axis=0) + margin_px, top)


def fiducial_view(fiducial_rc, shape, spacing, tube_radius_mm: float = DEFAULT_TUBE_RADIUS_MM):
    """(lo, hi) of the zoomed view: the fiducial's blobs (matched centres, predicted crossings) plus a margin.

    The margin leaves room for a blob and its label outside the ring of
    tubes: 20 % of the blobs' extent, at least four tube radii.
    """
    rc = np.asarray(fiducial_rc, dtype=float).reshape(-1, 2)
    if not rc.shape[0]:
        return view_bounds(rc, shape)
    extent = float(np.max(rc.max(axis=0) - rc.min(axis=0)))
    radius_px = tube_radius_mm / min(float(spacing[0]), float(spacing[1]))
    return view_bounds(rc, shape, max(0.2 * extent, 4.0 * radius_px, 8.0))


def scale_bar_mm(view_width_mm: float) -> float:
    """The longest of :data:`SCALE_BAR_MM` within a quarter of the view's width (at least the shortest)."""
    fitting = [v for v in SCALE_BAR_MM if v <= 0.25 * view_width_mm]
    return fitting[-1] if fitting else SCALE_BAR_MM[0]


def _draw_scale_bar(ax, lo, hi, col_spacing_mm: float):
    """A white bar of a round length in mm at the view's lower left; returns its (x0, y0, x1, y1) data box."""
    import matplotlib.patheffects as pe  # deferred: loads matplotlib only when used (one-shot start-up)

    width_px, height_px = hi[1] - lo[1], hi[0] - lo[0]
    length_mm = scale_bar_mm(width_px * col_spacing_mm)
    x0 = lo[1] + 0.05 * width_px
    x1 = x0 + length_mm / col_spacing_mm
    y = hi[0] - 0.06 * height_px
    outline = [pe.withStroke(linewidth=3.5, foreground="black")]
    ax.plot([x0, x1], [y, y], "-", color="white", lw=2.2, solid_capstyle="butt", gid=SCALE_BAR_GID,
            path_effects=outline)
    ax.text(0.5 * (x0 + x1), y - 0.015 * height_px, f"{length_mm:g} mm", color="white", fontsize=8, ha="center",
            va="bottom", gid=SCALE_BAR_LABEL_GID, path_effects=outline)
    return (x0, y - 0.09 * height_px, x1, y + 0.01 * height_px)


def _overlaps(a, b) -> bool:
    """Whether two (x0, y0, x1, y1) boxes (any corner order) intersect."""
    ax0, ax1 = sorted((a[0], a[2]))
    ay0, ay1 = sorted((a[1], a[3]))
    bx0, bx1 = sorted((b[0], b[2]))
    by0, by1 = sorted((b[1], b[3]))
    return ax0 < bx1 and bx0 < ax1 and ay0 < by1 and by0 < ay1


def _text_size_data(ax, text: str, fontsize: float, renderer):
    """(width, height) of ``text`` in data units (pixels of the image) at the axes' current scale."""
    t = ax.text(0, 0, text, fontsize=fontsize)
    bb = t.get_window_extent(renderer)
    t.remove()
    inv = ax.transData.inverted()
    (x0, y0), (x1, y1) = inv.transform([[bb.x0, bb.y0], [bb.x1, bb.y1]])
    return abs(x1 - x0), abs(y1 - y0)


def place_labels(ax, labels: dict, blobs_rc, radius_px: float, obstacles=(), fontsize: float = 8.0,
                 color: str = "lime") -> list:
    """Write each ``labels`` entry (tube id -> (row, col)) beside its blob, never on another label or blob.

    Each label goes outward from the centre of the labelled blobs; when that
    spot is taken it is turned aside and pushed further out, in steps, and a
    leader line joins it to its blob. ``blobs_rc`` (every candidate) and
    ``obstacles`` ((x0, y0, x1, y1) data boxes) are kept free. Returns the
    text artists (gid :data:`LABEL_GID`).
    """
    import matplotlib.patheffects as pe  # deferred: loads matplotlib only when used (one-shot start-up)

    if not labels:
        return []
    renderer = ax.figure.canvas.get_renderer()
    pts = {tid: np.array([float(rc[1]), float(rc[0])]) for tid, rc in labels.items()}  # (x = col, y = row)
    centre = np.mean(list(pts.values()), axis=0)
    r = radius_px
    taken = [tuple(b) for b in obstacles]
    taken += [(c - r, rw - r, c + r, rw + r) for rw, c in np.asarray(blobs_rc, dtype=float).reshape(-1, 2)]
    xlo, xhi = sorted(ax.get_xlim())
    ylo, yhi = sorted(ax.get_ylim())
    order = sorted(pts, key=lambda t: math.atan2(*(pts[t] - centre)[::-1]))
    artists = []
    outline = [pe.withStroke(linewidth=2.0, foreground="black")]
    for tid in order:
        p = pts[tid]
        w, h = _text_size_data(ax, tid, fontsize, renderer)
        w, h = w * 1.1 + 1.0, h * 1.05 + 1.0  # a little air around the glyphs
        d = p - centre
        base = math.atan2(d[1], d[0]) if np.hypot(*d) > 1e-9 else 0.0
        reach = r + 0.5 * math.hypot(w, h) + 1.0  # nearest spot whose box clears the blob
        best, best_cost = None, math.inf
        for k, step in enumerate((1.0, 1.5, 2.1, 2.8, 3.6, 4.5)):  # nearest first, then ever further out
            for turn in (0, 20, -20, 40, -40, 60, -60, 90, -90, 135, -135, 180):
                a = base + math.radians(turn)
                q = p + step * reach * np.array([math.cos(a), math.sin(a)])
                box = (q[0] - w / 2, q[1] - h / 2, q[0] + w / 2, q[1] + h / 2)
                inside = xlo <= box[0] and box[2] <= xhi and ylo <= box[1] and box[3] <= yhi
                cost = 1000 * sum(_overlaps(box, o) for o in taken) + (0 if inside else 500) + 10 * k + abs(turn) / 20
                if cost < best_cost:
                    best, best_cost = (q, box), cost
            if best_cost < 10 * (k + 1):  # a free spot inside the view at this reach
                break
        q, box = best
        taken.append(box)
        far = np.hypot(*(q - p)) > 1.05 * reach
        if far:  # a leader line from the blob's edge to the label
            u = (q - p) / np.hypot(*(q - p))
            start, end = p + u * r, q - u * 0.5 * min(w, h)
            ax.plot([start[0], end[0]], [start[1], end[1]], "-", color=color, lw=0.6, alpha=0.9)
        artists.append(ax.text(q[0], q[1], tid, color=color, fontsize=fontsize, ha="center", va="center",
                               gid=LABEL_GID, path_effects=outline, clip_on=True))
    return artists


def predicted_crossings_rc(geom, T_scanner_from_fiducial: np.ndarray, sl) -> dict:
    """``{tube id: (row, col)}``: where each tube of ``geom`` at a pose crosses slice ``sl`` (pixels)."""
    T_I_from_F = np.linalg.inv(sl.T_scanner_from_image()) @ np.asarray(T_scanner_from_fiducial, float)
    T_F_from_I = np.linalg.inv(T_I_from_F)
    rs, cs = (float(v) for v in sl.pixel_spacing_mm)
    out = {}
    for t in geom.tubes:
        for p in t.intersect_plane(T_F_from_I[:3, 3], T_F_from_I[:3, 2]):
            q = T_I_from_F[:3, :3] @ p + T_I_from_F[:3, 3]
            out[t.id] = (float(q[1] / rs), float(q[0] / cs))
    return out


def _results_per_slice(slices, registration) -> tuple[list, list]:
    """Per slice of ``slices``, its :class:`~chic_register.pipeline.results.SliceResult` and its
    :class:`~chic_register.pipeline.results.SkippedSlice` (None where there is none): matched by the slice's name,
    or by position where names repeat and every slice was used."""
    n = len(slices)
    if registration is None:
        return [None] * n, [None] * n
    names = [sl.source for sl in slices]
    if len(set(names)) < n and len(registration.slices) == n:
        return list(registration.slices), [None] * n
    used = {r.source: r for r in registration.slices}
    left_out = {s.source: s for s in registration.skipped}
    return [used.get(name) for name in names], [left_out.get(name) for name in names]


def overlay_figure(slices, registration=None, blobs=None, title: str | None = None,
                   tube_radius_mm: float = DEFAULT_TUBE_RADIUS_MM, predicted=None):
    """The overlay figure of ``slices`` (a list of Slice), not yet saved; see :func:`draw_overlay`."""
    import matplotlib  # deferred: loads matplotlib only when used (one-shot start-up)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # deferred: loads matplotlib only when used (one-shot start-up)
    from matplotlib.patches import Rectangle  # deferred: loads matplotlib only when used (one-shot start-up)

    n = len(slices)
    fig, axes = plt.subplots(n, 2, figsize=(10, 5.2 * n), squeeze=False, gridspec_kw={"width_ratios": [1, 1.25]})
    layout = []
    results, skips = _results_per_slice(slices, registration)
    for j, sl in enumerate(slices):
        img = np.asarray(sl.pixels, dtype=float)
        spacing = tuple(float(v) for v in sl.pixel_spacing_mm)
        res, skipped = results[j], skips[j]
        rc = res.blobs_rc if res is not None else (blobs[j].centres_rc if blobs is not None else np.zeros((0, 2)))
        rc = np.asarray(rc if rc is not None else np.zeros((0, 2)), dtype=float).reshape(-1, 2)
        pred = (np.array(list(res.predicted_rc.values()), dtype=float).reshape(-1, 2)
                if res is not None and res.predicted_rc else np.zeros((0, 2)))
        if res is not None and res.assignment:
            matched = rc[[int(b) for b in res.assignment.values()]]
            lo, hi = fiducial_view(np.vstack([matched, pred]), img.shape, spacing, tube_radius_mm)
        elif res is None and predicted is not None and predicted[j]:
            lo, hi = fiducial_view(np.array(list(predicted[j].values()), dtype=float).reshape(-1, 2), img.shape,
                                   spacing, tube_radius_mm)
        else:
            lo, hi = view_bounds(rc, img.shape)
        whole, ax = axes[j]
        vmin, vmax = np.percentile(img, [0.5, 99.8]) if img.size else (0.0, 1.0)
        for a in (whole, ax):
            a.imshow(img, cmap="gray", interpolation="nearest", vmin=vmin, vmax=max(vmax, vmin + 1e-12),
                     aspect=spacing[0] / spacing[1])
            a.set_xticks([])
            a.set_yticks([])
        whole.add_patch(Rectangle((lo[1], lo[0]), hi[1] - lo[1], hi[0] - lo[0], fill=False, ec="orange", lw=1.0,
                                  ls="--", gid=ZOOM_BOX_GID))
        whole.set_title(f"{Path(sl.source).name} (box: the zoomed view)", fontsize=9)
        ax.set_xlim(lo[1], hi[1])
        ax.set_ylim(hi[0], lo[0])
        if rc.shape[0]:
            ax.plot(rc[:, 1], rc[:, 0], "o", mfc="none", mec="yellow", ms=10, mew=1.0, label="candidate blobs")
        if res is not None:
            if res.ellipse is not None:
                e = _pixels_of_ellipse(res.ellipse, spacing)
                ax.plot(e[:, 1], e[:, 0], "-", color="deepskyblue", lw=0.8, label="ellipse fit")
            if pred.size:
                ax.plot(pred[:, 1], pred[:, 0], "+", color="red", ms=8, mew=1.0, label="model crossings")
            ax.set_title(f"depth {res.depth_mm:.2f} mm  tilt {res.tilt_deg:.2f}  twist {res.twist_deg:.2f} deg"
                         f"  rms {res.residual_rms_mm:.3f} mm", fontsize=9)
        else:
            if predicted is not None and predicted[j]:
                p = np.array(list(predicted[j].values()), dtype=float).reshape(-1, 2)
                ax.plot(p[:, 1], p[:, 0], "+", color="red", ms=10, mew=1.2,
                        label="the pose's crossings" if registration is not None else "refused pose's crossings")
                for tid, (r, c) in predicted[j].items():
                    if lo[0] <= r <= hi[0] and lo[1] <= c <= hi[1]:
                        ax.annotate(tid, (c, r), xytext=(6, 6), textcoords="offset points", color="red", fontsize=7)
            if skipped is not None:
                title_j = f"left out: {skipped.reason}"
                if skipped.residual_rms_mm is not None:
                    title_j += f" (rms {skipped.residual_rms_mm:.2f} mm under the pose)"
                ax.set_title("\n".join(textwrap.wrap(title_j, 70)), fontsize=8)
            else:
                ax.set_title(title or "no lock: candidates only", fontsize=9)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=3, fontsize=8, frameon=False)
        layout.append((ax, lo, hi, spacing, rc, res))
    fig.tight_layout()
    for ax, lo, hi, spacing, rc, res in layout:  # after the layout: label sizes are measured at the final scale
        bar = _draw_scale_bar(ax, lo, hi, spacing[1])
        if res is not None and res.assignment:
            labels = {tid: rc[int(b)] for tid, b in res.assignment.items()}
            radius_px = 1.15 * tube_radius_mm / min(spacing)
            place_labels(ax, labels, rc, radius_px, obstacles=[bar])
    return fig


def draw_overlay(path, slices, registration=None, blobs=None, title: str | None = None,
                 tube_radius_mm: float = DEFAULT_TUBE_RADIUS_MM, predicted=None) -> Path:
    """Write a PNG overlay of ``slices`` (list of Slice) to ``path``.

    ``registration``: a :class:`~chic_register.pipeline.register.Registration`
    (labels, ellipse, predictions); without it (no lock) only ``blobs`` (a list
    of :class:`~chic_register.detect.blobs.Blobs`, one per slice) are drawn, and
    ``predicted`` (per slice, ``{tube id: (row, col)}``: a refused pose's crossings).
    ``tube_radius_mm`` sizes the room kept around each blob.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ChicRegisterError(f"--overlay {path}: the overlay is a PNG file (give a name ending in .png)")
    fig = overlay_figure(slices, registration, blobs, title, tube_radius_mm, predicted)
    save_figure(fig, path)
    return path
