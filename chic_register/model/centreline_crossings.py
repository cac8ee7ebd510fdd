"""Where tube centrelines cross many planes at once: the crossings behind the envelope's plane checks.

:func:`plane_crossings` brackets one tube's centreline at samples and refines
the first bracket by Illinois regula falsi, for any number of planes at once;
:func:`tube_crossings` does the same for every tube of a geometry (straight
tubes together, helices with as many bracketing samples together: the
numbers are the same, numpy's per-call overhead is paid once, not per tube);
:func:`crossing_counts` counts the crossings alone. Used by
:mod:`chic_register.model.envelope` (which re-exports them) and the design checks.
"""

from __future__ import annotations

import functools

import numpy as np

from chic_register.model.tubes import (
    HelixTube,
    LineTube,
    helix_points,
    helix_tangents,
    line_points,
)


def _brackets(tube) -> tuple[np.ndarray, np.ndarray]:
    """``(params, points)``: a tube's bracketing samples and its centreline there (per tube, computed once;
    read-only)."""
    try:
        return _brackets_memo(tube)
    except TypeError:  # a tube object that is not hashable: no memo
        ts = tube.bracket_params()
        return ts, tube.points(ts)


@functools.lru_cache(maxsize=256)
def _brackets_memo(tube) -> tuple[np.ndarray, np.ndarray]:
    ts = tube.bracket_params()
    pts = tube.points(ts)
    ts.flags.writeable = pts.flags.writeable = False
    return ts, pts


def crossing_counts(tube, origins, normals) -> np.ndarray:
    """How many times a tube centreline crosses each plane (origins, normals: (P, 3)); shape (P,)."""
    pts = _brackets(tube)[1]
    g = np.asarray(normals, dtype=float) @ pts.T - np.einsum("pi,pi->p", origins, normals)[:, None]
    pos = g >= 0
    return (pos[:, 1:] != pos[:, :-1]).sum(axis=1)


def plane_crossings(tube, origins, normals, n_iter: int = 4):
    """Crossings of a tube centreline with many planes at once (vectorised ``intersect_plane``).

    ``origins``, ``normals``: shape (P, 3). The centreline is bracketed at
    samples (its two ends for a line, <= 2 mm apart otherwise) and each first
    bracket refined by Illinois regula falsi on ``tube.points``. Returns
    ``(t, points, tangents, count)``: shapes (P,), (P, 3), (P, 3), (P,); ``t``
    and the points are NaN where the plane misses the tube, ``count`` is the
    number of crossings.
    """
    o = np.asarray(origins, dtype=float)
    n = np.asarray(normals, dtype=float)
    ts, pts = _brackets(tube)  # (K,), (K, 3)
    off = np.einsum("pi,pi->p", o, n)
    g = n @ pts.T - off[:, None]  # (P, K)
    return _bracketed_crossings(np.broadcast_to(ts, g.shape), g, n, off, tube.points, tube.tangents, tube.curved,
                                n_iter)


def _bracketed_crossings(ts, g, n, off, points, tangents, curved: bool, n_iter: int = 4):
    """:func:`plane_crossings` from the bracketing samples ``ts`` (R, K) and the planes' values there ``g`` (R, K)
    (``n . x - off`` for planes ``n`` (R, 3), ``off`` (R,)); ``points``, ``tangents``: the centreline's at
    parameters (R,), row by row."""
    pos = g >= 0
    change = pos[:, 1:] != pos[:, :-1]
    count = change.sum(axis=1)
    hit = count > 0
    k = np.argmax(change, axis=1)
    rows = np.arange(len(g))
    ta, tb = ts[rows, k], ts[rows, k + 1]
    ga, gb = g[rows, k], g[rows, k + 1]
    denom = np.where(gb != ga, gb - ga, 1.0)
    t = ta - ga * (tb - ta) / denom
    if curved:
        side = np.zeros(len(t))  # +1: end a was replaced last time, -1: end b
        for _ in range(n_iter):
            gt = np.einsum("pi,pi->p", n, points(t)) - off
            same = np.sign(gt) == np.sign(ga)  # t replaces end a
            # Illinois: halve the kept end's value when the same end is replaced twice in a row
            ga, gb = (np.where(same, gt, np.where(side == -1, 0.5 * ga, ga)),
                      np.where(same, np.where(side == 1, 0.5 * gb, gb), gt))
            ta, tb = np.where(same, t, ta), np.where(same, tb, t)
            side = np.where(same, 1.0, -1.0)
            denom = np.where(gb != ga, gb - ga, 1.0)
            t = np.clip(ta - ga * (tb - ta) / denom, np.minimum(ta, tb), np.maximum(ta, tb))
    t = np.where(hit, t, np.nan)
    safe = np.where(hit, t, 0.0)
    points = np.where(hit[:, None], points(safe), np.nan)
    tangents = np.where(hit[:, None], tangents(safe), np.nan)
    return t, points, tangents, count


def tube_crossings(tubes, origins, normals):
    """:func:`plane_crossings` of every tube with every plane: ``(t (P, N), points (P, N, 3), tangents (P, N, 3),
    count (P, N))``, the same numbers, with the straight tubes all at once and the helices with as many bracketing
    samples all at once (a handful of planes costs numpy's per-call overhead once, not once per tube)."""
    o = np.asarray(origins, dtype=float)
    n = np.asarray(normals, dtype=float)
    P, N = len(n), len(tubes)
    tpar, C, T = np.empty((P, N)), np.empty((P, N, 3)), np.empty((P, N, 3))
    cnt = np.empty((P, N), dtype=int)
    off = np.einsum("pi,pi->p", o, n)
    try:
        groups = _tube_groups(tuple(tubes))
    except TypeError:  # a tube object that is not hashable: no memo
        groups = _tube_groups.__wrapped__(tuple(tubes))
    for kind, ks, ts, pts, params in groups:
        if kind == "other":
            tpar[:, ks[0]], C[:, ks[0]], T[:, ks[0]], cnt[:, ks[0]] = plane_crossings(tubes[ks[0]], o, n)
            continue
        G, K = ts.shape
        g = (n @ pts.reshape(-1, 3).T).reshape(P * G, K) - np.repeat(off, G)[:, None]
        each = [np.tile(v, (P, 1)) if v.ndim == 2 else np.tile(v, P) for v in params]  # a row per (plane, tube)
        if kind == "line":
            p0, d, direction = each

            def points(t, p0=p0, d=d):
                return line_points(p0, d, t)

            def tangents(t, direction=direction):
                return direction.copy()
        else:
            rad, th0, pitch, z0, z1 = each

            def points(t, rad=rad, th0=th0, pitch=pitch, z0=z0, z1=z1):
                return helix_points(rad, th0, pitch, z0, z0 + t * (z1 - z0))

            def tangents(t, rad=rad, th0=th0, pitch=pitch, z0=z0, z1=z1):
                return helix_tangents(rad, th0, pitch, z0, z1, t)

        t, pt, tg, c = _bracketed_crossings(np.tile(ts, (P, 1)), g, np.repeat(n, G, axis=0), np.repeat(off, G),
                                            points, tangents, kind == "helix")
        tpar[:, ks], C[:, ks], T[:, ks], cnt[:, ks] = t.reshape(P, G), pt.reshape(P, G, 3), tg.reshape(P, G, 3), \
            c.reshape(P, G)
    return tpar, C, T, cnt


@functools.lru_cache(maxsize=64)
def _tube_groups(tubes: tuple) -> list:
    """:func:`tube_crossings`' groups of tubes: ``(kind, indices, bracket params (G, K), bracket points (G, K, 3),
    centreline parameters)``, straight tubes together, helices with as many brackets together (computed once)."""
    by_kind: dict = {}
    for k, tube in enumerate(tubes):
        kind = ("line",) if isinstance(tube, LineTube) else ("helix", len(_brackets(tube)[0])) \
            if isinstance(tube, HelixTube) else ("other", k)
        by_kind.setdefault(kind, []).append(k)
    out = []
    for kind, ks in by_kind.items():
        group = [tubes[k] for k in ks]
        brackets = [_brackets(tube) for tube in group]
        ts, pts = np.stack([b[0] for b in brackets]), np.stack([b[1] for b in brackets])
        if kind[0] == "line":
            params = [np.stack(v) for v in zip(*((*tube._ends, tube.direction) for tube in group))]
        elif kind[0] == "helix":
            params = [np.array([getattr(tube, a) for tube in group], dtype=float)
                      for a in ("radius", "theta0_deg", "pitch_deg_per_mm", "z0", "z1")]
        else:
            params = []
        for a in (ts, pts, *params):
            a.flags.writeable = False
        out.append((kind[0], ks, ts, pts, params))
    return out
