"""The usable envelope of a fiducial: does one image plane show every tube once, inside the body, apart?

The plane checks behind ``chic-design check``'s tilt limits
(:mod:`chic_design.feasibility` imports them from here) and behind the
solver's envelope test of a found pose (:mod:`chic_register.verify.pixels`):
for a plane through the axis point ``(0, 0, depth)`` with a tilt and an
azimuth (twist is an in-plane rotation and changes nothing), every tube
centreline must cross it inside its own extent (``tube_outside_body``), only
once (``tube_crosses_twice:H0``), and no two cross-sections may come closer
than one pixel (``tubes_merge:H0/D0``), for the slice's pixel size and
thickness. See :mod:`chic_design.feasibility` for the section model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.model.centreline_crossings import (
    crossing_counts,
    plane_crossings,
    tube_crossings,
)
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import slab_reach_mm

OUTSIDE = "tube_outside_body"
_ROLE_RANK = {"helix": 0, "orientation": 1, "diametric": 2, "other": 3}


# ----------------------------------------------------------------------------- plane crossings


def plane_normals(tilt_deg, azimuth_deg) -> np.ndarray:
    """Unit normals of planes with these tilts/azimuths (pose.slice_frame convention); shape (..., 3)."""
    t = np.radians(np.asarray(tilt_deg, dtype=float))
    a = np.radians(np.asarray(azimuth_deg, dtype=float))
    t, a = np.broadcast_arrays(t, a)
    return np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=-1)


# ----------------------------------------------------------------------------- tilt limits


def pair_order(geom: FiducialGeometry) -> list[tuple[int, int]]:
    """All tube pairs, each ordered helix < orientation < diametric < other (``H0/D0``)."""
    idx = list(range(len(geom.tubes)))
    rank = sorted(idx, key=lambda i: (_ROLE_RANK.get(geom.tubes[i].role, 9), i))
    pos = {i: p for p, i in enumerate(rank)}
    pairs = []
    for i in idx:
        for j in idx:
            if i < j:
                pairs.append((i, j) if pos[i] < pos[j] else (j, i))
    return pairs


def _blob_gap(phi, dist, pi, qi, pj, qj, ai, aj, slice_mm):
    """Strip width between two blobs across the in-plane direction at angle ``phi`` from their centre line.

    Each blob is an ellipse (semi-minor a, semi-major a/cos(beta) along the
    tube's projection) plus a smear segment of slice*tan(beta) along it; its
    support along a unit in-plane e is ``a sqrt(1 + w^2) + slice/2 |w|`` with
    ``w = (e . t) / cos(beta)`` (p, q: w for e along / across the centre line).
    """
    c, s = np.cos(phi), np.sin(phi)
    wi = c * pi + s * qi
    wj = c * pj + s * qj
    hi = ai * np.sqrt(1 + wi**2) + 0.5 * slice_mm * np.abs(wi)
    hj = aj * np.sqrt(1 + wj**2) + 0.5 * slice_mm * np.abs(wj)
    return c * dist - hi - hj


def _max_blob_gap(dist, pi, qi, pj, qj, ai, aj, slice_mm, n_coarse: int = 61, n_golden: int = 14):
    """Distance between two convex blobs: the widest separating strip over all in-plane directions.

    Separating-axis theorem: max over e of (e . delta - h_i(e) - h_j(e)); < 0 when
    they overlap. Coarse sampling of the direction over +-90 deg from the
    centre line, then golden-section refinement around the best sample. Shapes (K,).
    """
    args = [a[:, None] for a in (dist, pi, qi, pj, qj, ai, aj)]
    phis = np.linspace(-np.pi / 2, np.pi / 2, n_coarse)
    vals = _blob_gap(phis[None, :], *args, slice_mm)
    vals = np.where(np.isnan(vals), -np.inf, vals)
    k = np.argmax(vals, axis=1)
    step = phis[1] - phis[0]
    lo, hi = phis[k] - step, phis[k] + step
    args = [a[:, 0] for a in args]
    r = (math.sqrt(5) - 1) / 2
    x1, x2 = hi - r * (hi - lo), lo + r * (hi - lo)
    f1, f2 = _blob_gap(x1, *args, slice_mm), _blob_gap(x2, *args, slice_mm)
    for _ in range(n_golden):
        left = f1 > f2  # the max lies in [lo, x2]
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x1n = np.where(left, hi - r * (hi - lo), x2)
        x2n = np.where(left, x1, lo + r * (hi - lo))
        f1n = np.where(left, _blob_gap(x1n, *args, slice_mm), f2)
        f2n = np.where(left, f1, _blob_gap(x2n, *args, slice_mm))
        x1, x2, f1, f2 = x1n, x2n, f1n, f2n
    best = np.maximum(np.maximum(f1, f2), vals.max(axis=1))
    return best


def _disc_union(tube, t_center, origins, normals, slice_mm, half_mm, n: int):
    """Disc-union samples of one tube's blob: centres (K, n, 3) in the plane, radii (K, n) (NaN = no disc).

    The tube is the union of balls of radius d/2 on its centreline; a ball at
    height h above the plane meets the slab |h| <= slice/2 in a set whose
    projection is the disc of radius sqrt((d/2)^2 - max(0, |h| - slice/2)^2).
    Centreline parameters: ``t_center`` (K,) +- ``half_mm`` (K,) of arc, clipped to [0, 1].
    """
    L = max(tube.length_mm, 1e-9)
    u = np.linspace(-1.0, 1.0, n)
    t = np.clip(t_center[:, None] + u[None, :] * (half_mm / L)[:, None], 0.0, 1.0)  # (K, n)
    p = tube.points(t.ravel()).reshape(t.shape + (3,))
    h = np.einsum("kni,ki->kn", p - origins[:, None, :], normals)
    c = p - h[..., None] * normals[:, None, :]
    r = tube.diameter / 2
    over = np.maximum(np.abs(h) - 0.5 * slice_mm, 0.0)
    with np.errstate(invalid="ignore"):
        rho = np.where(over < r, np.sqrt(np.maximum(r * r - over * over, 0.0)), np.nan)
    return t, c, rho


def clipped_disc_distance(c1, r1, c2, r2, G, f1, f2):
    """Distance between discs clipped to a half-plane {f >= 0} (f: in-plane distance to the face line).

    c1, c2: centres (..., 3); r1, r2: radii; G: unit in-plane gradient of f
    (broadcastable to c1); f1, f2: f at the centres. Exact: the closest pair is
    either the two arc points on the centre line (when both lie in the
    half-plane), or involves a point on the face line (a chord). Where the
    clipped discs overlap, returns ``|c1 - c2| - r1 - r2`` (< 0, a depth);
    where either is empty, +inf.
    """
    dv = c2 - c1
    dist = np.linalg.norm(dv, axis=-1)
    e = dv / np.where(dist > 0, dist, 1.0)[..., None]
    eg = np.sum(e * G, axis=-1)
    plain = dist - r1 - r2
    valid_a = (f1 + r1 * eg >= -1e-12) & (f2 - r2 * eg >= -1e-12)
    # chords on the face line, in a coordinate tau along it
    T = np.cross(np.cross(G, e), G)  # any in-plane vector along the line would do; use G x (e x G)
    Tn = np.linalg.norm(T, axis=-1)
    T = np.where(Tn[..., None] > 1e-12, T / np.where(Tn > 1e-12, Tn, 1.0)[..., None], 0.0)
    tau1, tau2 = np.sum(c1 * T, axis=-1), np.sum(c2 * T, axis=-1)
    with np.errstate(invalid="ignore"):
        l1 = np.sqrt(np.maximum(r1 * r1 - f1 * f1, 0.0))
        l2 = np.sqrt(np.maximum(r2 * r2 - f2 * f2, 0.0))
    has1, has2 = np.abs(f1) <= r1, np.abs(f2) <= r2
    chord = np.maximum(np.maximum(tau2 - l2 - (tau1 + l1), tau1 - l1 - (tau2 + l2)), 0.0)

    def seg_to_clipped(tau_s, l_s, has_s, tau_o, f_o, r_o, has_o):
        dt = np.maximum(np.maximum(tau_s - l_s - tau_o, tau_o - (tau_s + l_s)), 0.0)
        val = np.where(f_o >= 0, np.hypot(dt, f_o) - r_o, np.where(has_o, chord, np.inf))
        return np.where(has_s, np.maximum(val, 0.0), np.inf)

    b = seg_to_clipped(tau1, l1, has1, tau2, f2, r2, has2)
    c = seg_to_clipped(tau2, l2, has2, tau1, f1, r1, has1)
    out = np.minimum(np.where(valid_a, plain, np.inf), np.minimum(b, c))
    # overlapping discs: does their lens reach the half-plane?
    with np.errstate(invalid="ignore", divide="ignore"):
        a = (dist * dist + r1 * r1 - r2 * r2) / (2 * np.where(dist > 0, dist, 1.0))
        hgt = np.sqrt(np.maximum(r1 * r1 - a * a, 0.0))
    eperp_g = np.sqrt(np.maximum(1.0 - eg * eg, 0.0))
    cross_ok = (dist > np.abs(r1 - r2)) & (f1 + a * eg + hgt * eperp_g >= 0)
    top1 = (np.linalg.norm(c1 + r1[..., None] * G - c2, axis=-1) <= r2) & (f1 + r1 >= 0)
    top2 = (np.linalg.norm(c2 + r2[..., None] * G - c1, axis=-1) <= r1) & (f2 + r2 >= 0)
    lens_in = (plain < 0) & (cross_ok | top1 | top2)
    out = np.where(lens_in, plain, np.where(plain < 0, np.minimum(b, c), out))
    empty = (f1 < -r1) | (f2 < -r2) | np.isnan(r1) | np.isnan(r2)
    return np.where(empty, np.inf, out)


def section_gap(tube_a, tube_b, origins, normals, slice_thickness_mm: float, body_length_mm: float | None = None,
                t_a=None, t_b=None, n_samples: int = 17, n_zoom: int = 5):
    """Exact in-image gap (mm) between the blobs of two tubes on planes (origins, normals: (K, 3)).

    Each blob is the projection onto the plane of the tube (the union of balls
    of radius d/2 along its centreline, within its extent) cut by the slab of
    thickness ``slice_thickness_mm``: a union of discs (see
    :func:`_disc_union`), clipped by the end face (z = 0 or
    ``body_length_mm``, the one nearer the crossings; None: no clipping). The
    distance between two such sets is the smallest distance between a disc of
    one and a disc of the other (:func:`clipped_disc_distance`), found on an
    ``n_samples``^2 grid of centreline parameters around the crossings
    (``t_a``, ``t_b``: crossing parameters, computed if None), zoomed in
    ``n_zoom`` times. Negative = the blobs overlap (then only the sign is
    meaningful). Exact for helices, where the tangent-cylinder ellipse is
    not, and for blobs cut by an end face, with zero slice thickness; with a
    slab the face clip is the widest over the slab (the blobs can only be
    smaller, so the gap is conservative). Returns ``(gap, z_a, z_b)``: shape
    (K,) each, the gap and the z (mm) of the centreline points of the two closest discs.
    """
    o = np.asarray(origins, dtype=float).reshape(-1, 3)
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    if t_a is None:
        t_a = plane_crossings(tube_a, o, n)[0]
    if t_b is None:
        t_b = plane_crossings(tube_b, o, n)[0]
    t_a, t_b = np.asarray(t_a, dtype=float), np.asarray(t_b, dtype=float)
    K = len(o)
    gap = np.full(K, np.nan)
    za, zb = np.full(K, np.nan), np.full(K, np.nan)
    ok = np.isfinite(t_a) & np.isfinite(t_b)
    if not ok.any():
        return gap, za, zb
    o, n, ca, cb = o[ok], n[ok], t_a[ok], t_b[ok]
    S = float(slice_thickness_mm)
    halves = []
    for tube, tc in ((tube_a, ca), (tube_b, cb)):
        tg = tube.tangents(tc)
        cosb = np.abs(np.einsum("ki,ki->k", tg, n))
        halves.append(np.minimum(tube.slab_reach_mm(cosb, S, scale=1.05) + 0.1, tube.length_mm))
    ha, hb = halves
    # face half-plane f >= 0, f = sigma (x_z - z_face) / sin(tilt): in-plane distance to the face line
    sin_t = np.sqrt(np.maximum(1.0 - n[:, 2] ** 2, 0.0))
    zmid = 0.5 * (tube_a.points(ca)[:, 2] + tube_b.points(cb)[:, 2])
    clip = np.zeros(len(o), dtype=bool) if body_length_mm is None else sin_t > 1e-9
    L = 0.0 if body_length_mm is None else float(body_length_mm)
    sigma = np.where(zmid <= 0.5 * L, 1.0, -1.0)
    zface = np.where(sigma > 0, 0.0, L) - sigma * 0.5 * S * np.abs(n[:, 2])
    grad = np.array([0.0, 0.0, 1.0]) - n[:, 2:3] * n
    G = sigma[:, None] * grad / np.where(sin_t > 1e-9, sin_t, 1.0)[:, None]
    G = np.where(clip[:, None], G, 0.0)[:, None, None, :]
    rows = np.arange(len(o))
    for _ in range(n_zoom + 1):
        sa, pa, ra = _disc_union(tube_a, ca, o, n, S, ha, n_samples)
        sb, pb, rb = _disc_union(tube_b, cb, o, n, S, hb, n_samples)

        def f_of(p):
            return np.where(clip[:, None], sigma[:, None] * (p[..., 2] - zface[:, None])
                            / np.where(sin_t > 1e-9, sin_t, 1.0)[:, None], np.inf)

        fa, fb = f_of(pa), f_of(pb)
        fa, fb = np.where(np.isinf(fa), 1e9, fa), np.where(np.isinf(fb), 1e9, fb)
        d = clipped_disc_distance(pa[:, :, None, :], ra[:, :, None], pb[:, None, :, :], rb[:, None, :],
                                   G, fa[:, :, None], fb[:, None, :])
        d = np.where(np.isnan(d), np.inf, d).reshape(len(o), -1)
        k = np.argmin(d, axis=1)
        i, j = np.divmod(k, n_samples)
        best = d[rows, k]
        ca, cb = sa[rows, i], sb[rows, j]
        step = 2.0 / (n_samples - 1)
        ha, hb = ha * 1.5 * step, hb * 1.5 * step
    gap[ok] = best
    za[ok] = tube_a.points(ca)[:, 2]
    zb[ok] = tube_b.points(cb)[:, 2]
    return gap, za, zb

class PlaneChecker:
    """Evaluates the tilt constraints on many planes through the axis at once."""

    def __init__(self, geom: FiducialGeometry, pixel_size_mm: float, slice_thickness_mm: float,
                 merges: bool = True, exact: bool = True):
        self.geom = geom
        self.tubes = geom.tubes
        self.pixel = float(pixel_size_mm)
        self.slice = float(slice_thickness_mm)
        self.pairs = pair_order(geom) if merges else []
        self.I = np.array([p[0] for p in self.pairs], dtype=int)
        self.J = np.array([p[1] for p in self.pairs], dtype=int)
        self.semi = np.array([t.diameter / 2 for t in self.tubes])
        self.curved = np.array([t.curved for t in self.tubes])
        self.exact = exact
        n = len(self.tubes)
        self.labels = ["ok", OUTSIDE] + [f"tube_crosses_twice:{t.id}" for t in self.tubes] + [
            f"tubes_merge:{self.tubes[i].id}/{self.tubes[j].id}" for i, j in self.pairs
        ]
        self._merge0 = 2 + n

    def margins(self, depth_mm, tilt_deg, azimuth_deg):
        """Crossing counts (P, N) and merge margins (P, M) (mm; < 0 = merged) for planes (P,)."""
        z = np.asarray(depth_mm, dtype=float)
        normals = plane_normals(tilt_deg, azimuth_deg).reshape(-1, 3)
        origins = np.zeros_like(normals)
        origins[:, 2] = z
        P, N = len(normals), len(self.tubes)
        if len(self.pairs) == 0:  # visibility only: crossing counts suffice
            cnt = np.empty((P, N), dtype=int)
            for k, tube in enumerate(self.tubes):
                cnt[:, k] = crossing_counts(tube, origins, normals)
            return cnt, np.zeros((P, 0))
        tpar, C, T, cnt = tube_crossings(self.tubes, origins, normals)
        d = C[:, self.J] - C[:, self.I]  # (P, M, 3)
        dist = np.linalg.norm(d, axis=-1)
        e0 = d / np.where(dist > 0, dist, 1.0)[..., None]
        e1 = np.cross(normals[:, None, :], e0)  # in-plane, perpendicular to the centre line
        cosb = np.abs(np.einsum("pni,pi->pn", T, normals))  # (P, N) = cos(beta)
        with np.errstate(divide="ignore", invalid="ignore"):
            pi = np.einsum("pmi,pmi->pm", e0, T[:, self.I]) / cosb[:, self.I]
            qi = np.einsum("pmi,pmi->pm", e1, T[:, self.I]) / cosb[:, self.I]
            pj = np.einsum("pmi,pmi->pm", e0, T[:, self.J]) / cosb[:, self.J]
            qj = np.einsum("pmi,pmi->pm", e1, T[:, self.J]) / cosb[:, self.J]
        args = (dist, pi, qi, pj, qj, self.semi[self.I], self.semi[self.J])
        with np.errstate(invalid="ignore"):
            gap = _blob_gap(0.0, *args, self.slice)  # along the centre line: a lower bound
            rows, cols = np.nonzero((gap < self.pixel) & np.isfinite(gap))
            if rows.size:
                sub = [np.broadcast_to(a, gap.shape)[rows, cols] for a in args]
                gap[rows, cols] = _max_blob_gap(*sub, self.slice)
            if self.exact:
                self._exact_gaps(gap, origins, normals, C, cosb, tpar)
        margin = gap - self.pixel
        margin = np.where(np.isnan(dist), np.nan, np.where(np.isnan(margin), -np.inf, margin))
        return cnt, margin

    def _exact_gaps(self, gap, origins, normals, C, cosb, tpar, margin_mm: float = 0.1):
        """Replace, in place, the ellipse gaps (P, M) near or below one pixel by :func:`section_gap`.

        Only where the ellipse model is not exact: a pair with a helix, or a
        blob that may reach an end face (the face cuts it). The ellipse model
        is within a few hundredths of a mm of the truth or conservative, so
        pairs more than ``margin_mm`` above one pixel are left as they are.
        """
        L = self.geom.body.length
        with np.errstate(divide="ignore", invalid="ignore"):
            reach = slab_reach_mm(self.semi[None, :], cosb, self.slice) + 0.5 * self.slice
        near_face = (np.minimum(C[..., 2], L - C[..., 2]) < reach)  # (P, N)
        special = self.curved[self.I][None, :] | self.curved[self.J][None, :] | near_face[:, self.I] | near_face[:, self.J]
        rows, cols = np.nonzero(special & (gap < self.pixel + margin_mm) & np.isfinite(gap))
        for m in np.unique(cols):
            r = rows[cols == m]
            i, j = self.I[m], self.J[m]
            gap[r, m] = section_gap(self.tubes[i], self.tubes[j], origins[r], normals[r], self.slice,
                                    L, tpar[r, i], tpar[r, j])[0]

    def codes(self, depth_mm, tilt_deg, azimuth_deg, chunk: int = 20000) -> np.ndarray:
        """Label index (into ``self.labels``) of the failing constraint per plane; 0 = all pass."""
        z, t, a = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (depth_mm, tilt_deg, azimuth_deg)))
        z, t, a = z.ravel(), t.ravel(), a.ravel()
        out = np.zeros(z.size, dtype=int)
        for s in range(0, z.size, chunk):
            cnt, margin = self.margins(z[s:s + chunk], t[s:s + chunk], a[s:s + chunk])
            code = np.zeros(len(cnt), dtype=int)
            m = np.where(np.isnan(margin), np.inf, margin)
            if m.shape[1]:
                worst = np.argmin(m, axis=1)
                merged = m[np.arange(len(m)), worst] < 0
                code[merged] = self._merge0 + worst[merged]
            twice = cnt > 1
            code[twice.any(1)] = 2 + np.argmax(twice, axis=1)[twice.any(1)]
            code[(cnt == 0).any(1)] = 1
            out[s:s + chunk] = code
        return out


@dataclass(frozen=True)
class PlaneStatus:
    """The plane checks of one image plane.

    ``ok`` when every check passes; ``failure``: the first failing check's
    label as in :class:`PlaneChecker` (``tube_outside_body``,
    ``tube_crosses_twice:<id>``, ``tubes_merge:<id>/<id>``) or ``""``;
    ``outside``: ids of the tubes the plane misses, ``twice``: ids crossed
    more than once, ``merged``: id pairs whose sections come closer than one
    pixel (among the tubes crossed).
    """

    ok: bool
    failure: str
    outside: tuple[str, ...] = ()
    twice: tuple[str, ...] = ()
    merged: tuple[tuple[str, str], ...] = ()


def plane_status(geom: FiducialGeometry, depth_mm: float, tilt_deg: float, azimuth_deg: float,
                 pixel_size_mm: float, slice_thickness_mm: float, exact: bool = False) -> PlaneStatus:
    """The design's plane checks (the tilt limits' constraints) on one plane, for this pixel size and thickness.

    The failure named is the one :meth:`PlaneChecker.codes` names (missed,
    then crossed twice, then the worst merge). ``exact`` as in
    :func:`chic_design.feasibility.tilt_search.tilt_limits` (the ellipse model is within
    0.1 deg of the exact sections for the designs here, at a 15th of the cost).
    """
    checker = PlaneChecker(geom, pixel_size_mm, slice_thickness_mm, exact=exact)
    cnt, margin = checker.margins(np.array([float(depth_mm)]), float(tilt_deg), float(azimuth_deg))
    ids = [t.id for t in geom.tubes]
    # a tube that barely rises in z (an N-localizer's edge rods, across the box) is seen only by planes along it:
    # a plane across the axis that misses it is not outside the envelope
    flat = {k for k, t in enumerate(geom.tubes) if t.z_range[1] - t.z_range[0] < t.diameter}
    outside = tuple(ids[k] for k in np.flatnonzero(cnt[0] == 0) if k not in flat)
    twice = tuple(ids[k] for k in np.flatnonzero(cnt[0] > 1))
    merged = tuple((ids[checker.I[m]], ids[checker.J[m]]) for m in np.flatnonzero(margin[0] < 0)) if margin.size else ()
    failure = ("tube_outside_body" if outside else f"tube_crosses_twice:{twice[0]}" if twice else
               "" if not merged else checker.labels[checker._merge0 + int(np.nanargmin(margin[0]))])
    return PlaneStatus(not failure, failure, outside, twice, merged)
