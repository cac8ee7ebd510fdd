"""Which pixels each tube's section fit uses (:mod:`chic_register.fit.section`): its window.

A tube's window is its section's box grown by a margin, less the pixels a
neighbouring tube's section reaches or an unassigned blob covers, so that each
fit sees one tube; the joint pass's windows keep the pixels only fitted
neighbours reach. The boxes are enumerated once per pose (:func:`window_pixels`,
a :class:`Reach`), and only the pairs of tubes whose boxes can meet are tested
pixel by pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chic_register.model.tube_model import section_box, section_extent
from chic_register.util.quantiles import unique_ints


@dataclass(frozen=True, eq=False)
class Windows:
    """The pixels each tube's fit uses: ``rows``, ``cols`` (P,) and ``owner`` (P,), the tube index."""

    rows: np.ndarray
    cols: np.ndarray
    owner: np.ndarray
    shared: bool = True  # some pixel was left out for a neighbouring tube's sake (the joint pass has work)


def section_windows(model, q: np.ndarray, tan: np.ndarray, found: np.ndarray, todo: np.ndarray, shape,
                    pixel_spacing_mm, slice_thickness_mm: float, assignment=None, footprints=(),
                    margin_px: float = 1.5, reach=None) -> Windows:
    """Each tube in ``todo``'s section box grown by ``margin_px``, less what another tube or blob reaches.

    ``q``, ``tan``, ``found``: :func:`~chic_register.model.tube_model.plane_crossings`
    at the pose. Pixels within half a pixel of another tube's section box,
    or inside the footprint of a blob that is not the tube's own (nor
    overlaps it), are left out. ``reach``: :func:`window_pixels` of these
    arguments, when already computed.
    """
    reach = reach or window_pixels(model, q, tan, found, todo, shape, pixel_spacing_mm, slice_thickness_mm,
                                    margin_px)
    keep, shared = kept_pixels(reach, assignment, footprints)
    return Windows(reach.rows[keep], reach.cols[keep], reach.own[keep], shared)


@dataclass(eq=False)
class Reach:
    """Every tube in ``todo``'s bounding-box pixels ``rows``, ``cols``, ``own`` (P,); ``far`` (P,): the box's
    corners beyond the tube's own grown section box; ``(pair_p, pair_o)`` (M,): the pixels (ascending, then by
    tube) another found tube's grown section box reaches, and that tube (index into the model)."""

    rows: np.ndarray
    cols: np.ndarray
    own: np.ndarray
    far: np.ndarray
    pair_p: np.ndarray
    pair_o: np.ndarray
    _foreign: tuple | None = None

    def foreign(self, assignment, footprints) -> np.ndarray:
        """(P,) bool: pixels inside an unassigned blob's footprint that does not overlap the tube's own
        (:func:`_drop_foreign_blobs`; kept for the same ``assignment`` and ``footprints``)."""
        if self._foreign is not None and self._foreign[0] is footprints and np.array_equal(self._foreign[1],
                                                                                           assignment):
            return self._foreign[2]
        keep = np.ones(self.own.size, bool)
        _drop_foreign_blobs(keep, self.rows, self.cols, self.own, assignment, footprints)
        self._foreign = (footprints, np.array(assignment), ~keep)
        return ~keep


def window_pixels(model, q, tan, found, todo, shape, pixel_spacing_mm, slice_thickness_mm: float,
                   margin_px: float, lost=None) -> Reach:
    """Every tube in ``todo``'s bounding-box pixels, which other found tubes' section boxes (grown by a pixel)
    reach each, and which lie beyond the tube's own grown box: a :class:`Reach`. ``lost``: (rows, cols) bool,
    pixels lost to dropout (:mod:`chic_register.detect.dropout`), counted as beyond the box (no window keeps them).

    (Only the pairs of tubes whose boxes can overlap are tested, pixel by pixel: the same tests and values as
    testing every pixel against every tube, at a fraction of the work.)"""
    rs, cs = (float(v) for v in pixel_spacing_mm)
    H, W = shape
    half_len, _, u = section_extent(model, tan, slice_thickness_mm)
    half_wid = 0.5 * model.diameter_mm  # across its length a section is the tube's width
    u = np.where((np.abs(u).sum(axis=1) > 0)[:, None], u, [1.0, 0.0])  # a round section: any direction
    m_mm = margin_px * max(rs, cs)
    ex, ey = (e + m_mm for e in section_box(half_len, half_wid, u))
    qx, qy = q.T.copy()  # (contiguous rows: 1-d gathers, several times cheaper than 2-d fancy indexing)
    i0 = np.maximum(0, np.ceil((qy[todo] - ey[todo]) / rs)).astype(int)
    i1 = np.minimum(H - 1, np.floor((qy[todo] + ey[todo]) / rs)).astype(int)
    j0 = np.maximum(0, np.ceil((qx[todo] - ex[todo]) / cs)).astype(int)
    j1 = np.minimum(W - 1, np.floor((qx[todo] + ex[todo]) / cs)).astype(int)
    h, w = np.maximum(i1 - i0 + 1, 0), np.maximum(j1 - j0 + 1, 0)
    n = h * w
    first = np.cumsum(n) - n
    idx = np.repeat(np.arange(todo.size), n)
    local = np.arange(int(n.sum())) - first[idx]
    wi = np.maximum(w, 1)[idx]
    rr = i0[idx] + local // wi
    cc = j0[idx] + local % wi
    own = todo[idx]
    x_mm, y_mm = cc * cs, rr * rs
    u_rows = u.T.copy()
    dx, dy = x_mm - qx[own], y_mm - qy[own]
    ux, uy = u_rows[0][own], u_rows[1][own]
    # the corners of the bounding box that lie beyond the margin of the tube's own (rotated) section box
    far = ((np.abs(dx * ux + dy * uy) > half_len[own] + m_mm) | (np.abs(dx * uy - dy * ux) > half_wid[own] + m_mm))
    if lost is not None:
        far |= lost[rr, cc]
    # what another tube's section (grown by a pixel) reaches: first the pairs of tubes (a in todo, o found) whose
    # boxes' axis-aligned bounds can meet (|u| need not be 1: a bound for any u), then their pixels one by one
    grow = max(rs, cs)
    others = np.flatnonzero(found)
    u2 = np.einsum("ij,ij->i", u, u)
    ax = (np.abs(u[:, 0]) * (half_len + grow) + np.abs(u[:, 1]) * (half_wid + grow)) / u2 * (1 + 1e-6) + 1e-6
    ay = (np.abs(u[:, 1]) * (half_len + grow) + np.abs(u[:, 0]) * (half_wid + grow)) / u2 * (1 + 1e-6) + 1e-6
    qxo, qyo, axo, ayo = qx[others], qy[others], ax[others], ay[others]
    meet = ((j0 * cs)[:, None] <= (qxo + axo)[None]) & ((j1 * cs)[:, None] >= (qxo - axo)[None])
    meet &= ((i0 * rs)[:, None] <= (qyo + ayo)[None]) & ((i1 * rs)[:, None] >= (qyo - ayo)[None])
    meet &= others[None] != todo[:, None]
    meet &= (n > 0)[:, None]
    ta, oc = np.nonzero(meet)  # (by tube a, then other)
    if ta.size == 0:
        empty = np.zeros(0, int)
        return Reach(rr, cc, own, far, empty, empty)
    # each pair's pixels: pixel-major within a tube's box so that, a tube's pairs being contiguous, sorting is by
    # (pixel, other) once the blocks are laid out pixel by pixel
    m_a = np.bincount(ta, minlength=todo.size)  # other tubes met per tube
    pair0 = np.cumsum(m_a) - m_a  # each tube's first pair
    size = n * m_a
    bfirst = np.cumsum(size) - size
    a_of = np.repeat(np.arange(todo.size), size)
    t = np.arange(int(size.sum())) - bfirst[a_of]
    mm = m_a[a_of]
    p = first[a_of] + t // mm
    o = others[oc[pair0[a_of] + t % mm]]
    ddx, ddy = x_mm[p] - qx[o], y_mm[p] - qy[o]
    uox, uoy = u_rows[0][o], u_rows[1][o]
    hit = (np.abs(ddx * uox + ddy * uoy) < half_len[o] + grow) & (np.abs(ddx * uoy - ddy * uox) < half_wid[o] + grow)
    return Reach(rr, cc, own, far, p[hit], o[hit])


def kept_pixels(reach: Reach, assignment, footprints, modelled=None):
    """(P,) bool: the pixels of ``reach`` a window keeps: not beyond the tube's own box, not reached by another
    tube's section (with ``modelled`` (K,) given: by one not modelled), not in a foreign blob's footprint; and
    whether a window (``modelled`` None) left a pixel out for a neighbour's sake only."""
    hit = np.zeros(reach.own.size, bool)
    hit[reach.pair_p if modelled is None else reach.pair_p[~modelled[reach.pair_o]]] = True
    keep = ~(hit | reach.far)
    shared = modelled is None and bool((hit & ~reach.far).any())
    if len(footprints) and assignment is not None:
        keep &= ~reach.foreign(assignment, footprints)
    return keep, shared


def joint_windows(model, q: np.ndarray, tan: np.ndarray, found: np.ndarray, todo: np.ndarray, shape,
                  pixel_spacing_mm, slice_thickness_mm: float, modelled: np.ndarray, assignment=None, footprints=(),
                  margin_px: float = 1.5, reach=None, lost=None):
    """:func:`section_windows` keeping the pixels that only ``modelled`` (K,) tubes' sections reach besides the
    tube's own, and those pairs: ``(windows, pixel (M,) index into the windows, tube (M,))``.

    A pixel two sections share carries information on both: with the
    neighbour's fitted section subtracted (the joint pass of
    :func:`fit_sections`) it is used instead of left out, which matters where
    a helix runs close to a straight tube (near the body's ends). ``reach``: as for :func:`section_windows`;
    ``lost``: (rows, cols) bool, pixels no window keeps (lost to dropout).
    """
    reach = reach or window_pixels(model, q, tan, found, todo, shape, pixel_spacing_mm, slice_thickness_mm,
                                    margin_px, lost)
    return joint_windows_from_reach(reach, assignment, footprints, modelled)[:3]


def joint_windows_from_reach(reach: Reach, assignment, footprints, modelled):
    """:func:`joint_windows` from ``reach``, and the (P,) mask of its pixels that it keeps."""
    keep, _ = kept_pixels(reach, assignment, footprints, modelled)
    pair = keep[reach.pair_p]
    p = (np.cumsum(keep) - 1)[reach.pair_p[pair]]  # (the pairs stay ordered by pixel, then tube)
    return Windows(reach.rows[keep], reach.cols[keep], reach.own[keep]), p, reach.pair_o[pair], keep


def _drop_foreign_blobs(keep, rr, cc, own, assignment, footprints) -> None:
    """Clear ``keep`` on window pixels inside an unassigned blob's footprint that does not overlap the tube's own."""
    assigned = {int(b) for b in assignment if b >= 0}
    for n, (r0, c0, m) in enumerate(footprints):
        if n in assigned:
            continue
        h, w = m.shape
        inside = (rr >= r0) & (rr < r0 + h) & (cc >= c0) & (cc < c0 + w)
        if not inside.any():
            continue
        for k in unique_ints(own[inside]).tolist():
            R0, C0, M = footprints[int(assignment[k])]
            a0, b0 = max(r0, R0), max(c0, C0)
            a1, b1 = min(r0 + h, R0 + M.shape[0]), min(c0 + w, C0 + M.shape[1])
            if a0 < a1 and b0 < b1:
                theirs, mine = m[a0 - r0:a1 - r0, b0 - c0:b1 - c0], M[a0 - R0:a1 - R0, b0 - C0:b1 - C0]
                if (theirs & mine).any():
                    continue  # a split half of the tube's own blob, or the whole of it
            sel = np.flatnonzero(inside & (own == k))
            keep[sel[m[rr[sel] - r0, cc[sel] - c0]]] = False
