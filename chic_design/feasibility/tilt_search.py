"""Tilt limits and usable depth: the largest image tilt at each depth, searched over azimuths.

Items 1 and 2 of :mod:`chic_design.feasibility.engine`: for planes through the axis
point ``(0, 0, z)``, the first tilt at which a plane check of
:class:`chic_register.model.envelope.PlaneChecker` fails (tube outside the body,
crossed twice, sections merging), on a tilt grid then by bisection, the worst
case over azimuths; and the depth ranges usable at given tilts.
"""

from __future__ import annotations

import math

import numpy as np

from chic_design.feasibility.records import TiltLimit, UsableDepth
from chic_design.feasibility.runs import true_runs
from chic_register.model.envelope import PlaneChecker
from chic_register.model.geometry import FiducialGeometry

USABLE_TILTS_DEG = (0.0, 15.0, 30.0, 45.0)
TILT_CAP_DEG = 89.0
NO_LIMIT = "none_below_89_deg"


def _max_tilt(checker: PlaneChecker, z: np.ndarray, az: np.ndarray, grid_step: float = 5.0,
              tol_deg: float = 0.05):
    """Per (depth, azimuth) pair: first failing tilt (grid, then bisection). Returns tilt, code, ok0."""
    grid = np.append(np.arange(0.0, TILT_CAP_DEG, grid_step), TILT_CAP_DEG)
    P = z.size
    k = np.full(P, grid.size)  # index of the first failing grid tilt
    first_code = np.zeros(P, dtype=int)
    alive = np.arange(P)
    for i, g in enumerate(grid):  # only planes that have not failed yet
        if not alive.size:
            break
        c = checker.codes(z[alive], g, az[alive])
        bad = c != 0
        k[alive[bad]] = i
        first_code[alive[bad]] = c[bad]
        alive = alive[~bad]
    anyfail = k < grid.size
    ok0 = k > 0
    tilt = np.where(anyfail, 0.0, TILT_CAP_DEG)
    code = np.where(k == 0, first_code, 0)
    sel = np.flatnonzero(anyfail & (k > 0))
    if sel.size:
        lo, hi = grid[k[sel] - 1], grid[k[sel]]
        hic = first_code[sel]
        while np.max(hi - lo) > tol_deg:
            mid = 0.5 * (lo + hi)
            c = checker.codes(z[sel], mid, az[sel])
            bad = c != 0
            hi = np.where(bad, mid, hi)
            hic = np.where(bad, c, hic)
            lo = np.where(bad, lo, mid)
        tilt[sel] = lo
        code[sel] = hic
    return tilt, code, ok0


def depth_samples(length_mm: float, step_mm: float = 1.0) -> np.ndarray:
    """Depths from 0 to ``length_mm`` at <= ``step_mm``, both ends and mid-depth included."""
    n = max(2, int(math.ceil(length_mm / step_mm)))
    n += n % 2  # even number of intervals: mid-depth is a sample
    return np.linspace(0.0, length_mm, n + 1)


def tilt_limits(geom: FiducialGeometry, pixel_size_mm: float, slice_thickness_mm: float,
                depths_mm=None, azimuth_step_deg: float = 10.0, refine_step_deg: float = 0.5,
                merges: bool = True, exact: bool = False) -> tuple[TiltLimit, ...]:
    """Max tilt at each depth (default :func:`depth_samples`), worst case over azimuth.

    Azimuths on a ``azimuth_step_deg`` grid, then a ``refine_step_deg`` grid of
    +-``azimuth_step_deg`` around each depth's worst azimuth. Twist is an
    in-plane rotation of the image and changes none of the constraints.
    ``merges=False`` checks visibility (tubes inside the body, crossed once) only.
    ``exact=True`` replaces the ellipse gap of pairs with a helix or a blob cut
    by an end face, where it is within ``0.1 mm`` of one pixel, by the exact
    :func:`~chic_register.model.envelope.section_gap` (about 15x slower; for designs/neuro.yaml it gives the
    same limits to 0.1 deg, so :func:`~chic_design.feasibility.engine.check_geometry` uses the ellipse model).
    """
    checker = PlaneChecker(geom, pixel_size_mm, slice_thickness_mm, merges=merges, exact=exact)
    zs = depth_samples(geom.body.length) if depths_mm is None else np.asarray(depths_mm, dtype=float)
    azs = np.arange(0.0, 360.0, azimuth_step_deg)
    Z, A = np.meshgrid(zs, azs, indexing="ij")
    tilt, code, ok0 = (v.reshape(Z.shape) for v in _max_tilt(checker, Z.ravel(), A.ravel()))
    w = np.argmin(tilt, axis=1)
    rows = np.arange(len(zs))
    best_t, best_c, best_a = tilt[rows, w], code[rows, w], A[rows, w]
    usable0 = ok0.all(axis=1)
    # refine azimuth around the worst one (where something above tilt 0 limits it)
    need = usable0 & (best_t < TILT_CAP_DEG)
    if need.any():
        # bracket each neighbour azimuth in [worst - 3, worst + tol]: only lower limits matter
        off = np.arange(-azimuth_step_deg, azimuth_step_deg + 1e-9, refine_step_deg)
        rows2 = np.repeat(np.flatnonzero(need), off.size)
        Z2 = zs[rows2]
        A2 = (best_a[rows2] + np.tile(off, need.sum())) % 360.0
        hi = best_t[rows2] + 0.05
        lo = np.maximum(best_t[rows2] - 3.0, 0.0)
        c_lo = checker.codes(Z2, lo, A2)
        low_fail = c_lo != 0
        t2 = np.empty(Z2.size)
        c2 = np.zeros(Z2.size, dtype=int)
        if low_fail.any():  # rare: far lower than the grid showed; search from tilt 0
            t2[low_fail], c2[low_fail], _ = _max_tilt(checker, Z2[low_fail], A2[low_fail])
        ok = np.flatnonzero(~low_fail)
        lo, hi, hic = lo[ok], hi[ok], np.zeros(ok.size, dtype=int)
        while ok.size and np.max(hi - lo) > 0.05:
            mid = 0.5 * (lo + hi)
            c = checker.codes(Z2[ok], mid, A2[ok])
            bad = c != 0
            hi, hic, lo = np.where(bad, mid, hi), np.where(bad, c, hic), np.where(bad, lo, mid)
        t2[ok], c2[ok] = lo, hic
        for r in np.flatnonzero(need):
            m = rows2 == r
            j = np.argmin(np.where(c2[m] != 0, t2[m], np.inf))
            if c2[m][j] != 0 and t2[m][j] < best_t[r]:
                best_t[r], best_c[r], best_a[r] = t2[m][j], c2[m][j], A2[m][j]
    return tuple(
        TiltLimit(float(z), float(t) if u else 0.0, checker.labels[int(c)] if c else NO_LIMIT,
                  float(a), bool(u))
        for z, t, c, a, u in zip(zs, best_t, best_c, best_a, usable0)
    )


def usable_depth(limits, tilts_deg=USABLE_TILTS_DEG) -> tuple[UsableDepth, ...]:
    """Contiguous runs of depth samples usable at each tilt (range ends are sample depths)."""
    zs = np.array([t.depth_mm for t in limits])
    out = []
    for tilt in tilts_deg:
        ok = np.array([t.usable_at_zero_tilt and t.max_tilt_deg >= tilt for t in limits])
        out.append(UsableDepth(float(tilt), true_runs(zs, ok)))
    return tuple(out)
