"""The pose solver: detected tube centres in one or more slices -> the fiducial's 6-DOF pose.

The chain follows the paper, then goes further:

1. a robust ellipse fit of the blob centres (image mm) gives the centre of
   the cross-section, the tilt (``acos(minor/major)``) and the direction of
   the major axis (the azimuth, up to a two-fold sign);
2. "unrolling" every blob onto the cylinder (angle about the axis and height
   relative to the centre) for each of the four sign choices (which end of
   the major axis is up; which side the image is viewed from), the tubes that
   are straight and parallel to the axis fix the rotation about the axis (the
   twist) and the helices fix the depth (:meth:`HelixTube.z_at_angle`);
3. every resulting hypothesis is refined on all six degrees of freedom by
   Gauss-Newton on the model: the predicted crossings of every tube
   centreline of the geometry file with the image plane against the detected
   centres, with the blob-to-tube assignment re-solved (Hungarian) on the
   way, so extra and missing blobs are simply left unassigned;
4. trust checks turn every doubtful outcome into :class:`NoLock`.

Several slices are registered jointly: one ``T_scanner_from_fiducial`` fitted
to the correspondences of every slice. Nothing here assumes the CHIC layout:
the tube list, roles and angles all come from the geometry file.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass, field

import numpy as np

from .detect import Blobs, _dilate, detect_blobs, median
from .errors import ImprecisePose, NoLock
from .geometry import FiducialGeometry, HelixTube, LineTube, content_sha256
from .matching import gated_matching
from .hypotheses import (  # noqa: F401  (the first-guess stage; its public names stay importable from here)
    Ellipse,
    ellipse_layout,
    family_hypotheses,
    fit_ellipse_robust,
    initial_hypotheses,
    parallel_family,
)
from .pose import invert, rigid, slice_angles
from .slices import Slice

# --------------------------------------------------------------------------- model


@dataclass(frozen=True, eq=False)
class TubeModel:
    """The geometry file's tube centrelines as arrays, for vectorised predictions.

    K tubes; line tubes use ``p0``/``d`` (K, 3), helices use ``radius``,
    ``theta0_rad``, ``omega_rad_per_mm``, ``z0`` (K,) (NaN where unused).
    ``axial`` marks lines parallel to the z axis (constant angle
    ``angle_rad``); ``depth_coding`` marks tubes not parallel to the axis
    (they tell the depth).
    """

    ids: tuple[str, ...]
    roles: tuple[str, ...]
    is_helix: np.ndarray
    p0: np.ndarray
    d: np.ndarray
    radius: np.ndarray
    theta0_rad: np.ndarray
    omega_rad_per_mm: np.ndarray
    z0: np.ndarray
    z_lo: np.ndarray
    z_hi: np.ndarray
    axial: np.ndarray
    angle_rad: np.ndarray
    axis_radius_mm: np.ndarray
    depth_coding: np.ndarray
    diameter_mm: np.ndarray
    length_mm: float
    line_idx: np.ndarray = None
    helix_idx: np.ndarray = None
    line_p0: np.ndarray = None
    line_d: np.ndarray = None
    line_dunit: np.ndarray = None
    line_params: tuple = ()
    helix_params: tuple = ()
    tubes: tuple = ()  # the geometry's tube objects (sampled by the generic first guess)

    def __post_init__(self):
        li, hi = np.flatnonzero(~self.is_helix), np.flatnonzero(self.is_helix)
        d = self.d[li]
        object.__setattr__(self, "line_idx", li)
        object.__setattr__(self, "helix_idx", hi)
        object.__setattr__(self, "line_p0", self.p0[li].copy())
        object.__setattr__(self, "line_d", d.copy())
        object.__setattr__(self, "line_dunit", d / np.linalg.norm(d, axis=1, keepdims=True))
        object.__setattr__(self, "line_params", tuple(
            (int(k), *(float(v) for v in self.p0[k]), *(float(v) for v in self.d[k]),
             *(float(v) for v in self.d[k] / np.linalg.norm(self.d[k]))) for k in li))
        object.__setattr__(self, "helix_params", tuple(
            (int(k), float(self.radius[k]), float(self.theta0_rad[k]), float(self.omega_rad_per_mm[k]),
             float(self.z0[k])) for k in hi))

    @classmethod
    def from_geometry(cls, geom: FiducialGeometry) -> "TubeModel":
        K = len(geom.tubes)
        nan = np.full(K, np.nan)
        p0, d = np.full((K, 3), np.nan), np.full((K, 3), np.nan)
        radius, th0, om, z0 = nan.copy(), nan.copy(), nan.copy(), nan.copy()
        z_lo, z_hi = np.zeros(K), np.zeros(K)
        axial, is_helix = np.zeros(K, bool), np.zeros(K, bool)
        angle, rad_axis = nan.copy(), np.zeros(K)
        for k, t in enumerate(geom.tubes):
            z_lo[k], z_hi[k] = t.z_range
            if isinstance(t, HelixTube):
                is_helix[k] = True
                radius[k], th0[k] = t.radius, math.radians(t.theta0_deg)
                om[k], z0[k] = math.radians(t.pitch_deg_per_mm), t.z0
                rad_axis[k] = t.radius
            elif isinstance(t, LineTube):
                p0[k], d[k] = t.p0, np.subtract(t.p1, t.p0)
                direction = t.direction
                mid = (np.asarray(t.p0) + np.asarray(t.p1)) / 2
                rad_axis[k] = math.hypot(mid[0], mid[1])
                if abs(direction[2]) > 1 - 1e-9 and rad_axis[k] > 1e-9:
                    axial[k] = True
                    angle[k] = math.atan2(mid[1], mid[0])
        return cls(
            ids=geom.ids,
            roles=tuple(t.role for t in geom.tubes),
            is_helix=is_helix, p0=p0, d=d, radius=radius, theta0_rad=th0,
            omega_rad_per_mm=om, z0=z0, z_lo=z_lo, z_hi=z_hi, axial=axial,
            angle_rad=angle, axis_radius_mm=rad_axis, depth_coding=~axial,
            diameter_mm=np.array([t.diameter for t in geom.tubes], float),
            length_mm=float(geom.body.length),
            tubes=tuple(geom.tubes),
        )


class _GeometryKey:
    """A hashable stand-in for a :class:`FiducialGeometry` (whose ``source`` dict is not hashable).

    Equal keys mean equal content (name, units, body, tubes, source, by
    their ``repr``, which tells -0.0 from 0.0 as the content hash does), so a
    memo keyed by it never serves one geometry's model or hash for another's.
    """

    __slots__ = ("_hash", "geom", "key")

    def __init__(self, geom: FiducialGeometry):
        src = geom.source
        frozen_src = None if src is None else tuple(sorted((str(k), repr(v)) for k, v in src.items()))
        self.geom = geom
        self.key = (geom.name, geom.units, repr(geom.body), repr(geom.tubes), frozen_src)
        self._hash = hash(self.key)

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other) -> bool:
        return isinstance(other, _GeometryKey) and self.key == other.key


@functools.lru_cache(maxsize=8)
def _prepared(key: _GeometryKey) -> tuple[TubeModel, str]:
    """The tube model and the content hash of a geometry, computed once per distinct geometry."""
    return TubeModel.from_geometry(key.geom), content_sha256(key.geom.content())


def prepare_geometry(geom: FiducialGeometry) -> tuple[TubeModel, str]:
    """``(TubeModel, content sha256)`` of ``geom``, memoised on its content (repeat calls cost ~10 us)."""
    try:
        return _prepared(_GeometryKey(geom))
    except TypeError:  # an unhashable value somewhere: no memo
        return TubeModel.from_geometry(geom), content_sha256(geom.content())


def plane_crossings(model: TubeModel, T_F_from_I: np.ndarray, margin_mm: float = 0.0):
    """Where every tube centreline crosses the image plane z_I = 0.

    Returns ``(xy_mm (K, 2), tangent_I (K, 3), z_F (K,), inside (K,) bool)``:
    the crossing in image-frame mm, the centreline's unit tangent in the
    image frame there, its height in F and whether it lies within the tube's
    extent widened by ``margin_mm`` (and was found). Lines: closed form;
    helices: Newton on z started from the axis crossing (scalar code: the
    arrays are tiny and numpy's per-call overhead would dominate).
    """
    R = T_F_from_I[:3, :3]
    o = T_F_from_I[:3, 3]
    (_, _, nx, ox), (_, _, ny, oy), (_, _, nz, oz) = T_F_from_I[:3].tolist()
    no = nx * ox + ny * oy + nz * oz  # the plane: x . n = no
    K = len(model.ids)
    rows = [None] * K  # per tube: crossing (3), unit tangent (3), found; all in F
    for k, px, py, pz, dx, dy, dz, ux, uy, uz in model.line_params:
        denom = dx * nx + dy * ny + dz * nz
        safe = abs(denom) > 1e-9
        t = (no - (px * nx + py * ny + pz * nz)) / (denom if safe else 1.0)
        rows[k] = (px + t * dx, py + t * dy, pz + t * dz, ux, uy, uz, safe)
    if model.helix_params:
        z_axis = no / nz if abs(nz) > 1e-9 else 0.0
        cos, sin = math.cos, math.sin
        for k, r, th0, om, z0 in model.helix_params:
            z = z_axis
            rnx, rny = r * nx, r * ny
            good = False
            for _ in range(30):
                th = th0 + om * (z - z0)
                c, s = cos(th), sin(th)
                dg = om * (rny * c - rnx * s) + nz
                step = (rnx * c + rny * s + nz * z - no) / (dg if abs(dg) > 1e-9 else 1e-9)
                step = max(-20.0, min(20.0, step))
                z -= step
                if abs(step) < 1e-11:
                    good = True
                    break
            th = th0 + om * (z - z0)
            c, s = cos(th), sin(th)
            vx, vy = -r * om * s, r * om * c
            inv = 1.0 / math.sqrt(vx * vx + vy * vy + 1.0)
            rows[k] = (r * c, r * s, z, vx * inv, vy * inv, inv,
                       good and abs(rnx * c + rny * s + nz * z - no) < 1e-6)
    A = np.array(rows, dtype=float).reshape(K, 7)
    X, tan, ok = A[:, :3], A[:, 3:6], A[:, 6] > 0
    zF = X[:, 2]
    tan_I = tan @ R
    if margin_mm > 0:
        lo, hi = model.z_lo - margin_mm, model.z_hi + margin_mm
    else:
        # strict: the whole cross-section must lie within the tube, else the blob is cut short by the
        # tube's end and its centre is biased: half the cut's length along the tube, in z of F
        cos_a = np.maximum(np.abs(tan_I[:, 2]), 1e-6)
        clear = 0.5 * model.diameter_mm * np.sqrt(np.maximum(1 - cos_a * cos_a, 0.0)) / cos_a * np.abs(tan[:, 2])
        lo, hi = model.z_lo + clear, model.z_hi - clear
    inside = ok & (zF >= lo - 1e-6) & (zF <= hi + 1e-6)
    q = (X - o) @ R  # rows: R^T (X - o)
    return q[:, :2], tan_I, zF, inside


def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of vectors (..., 3) -> (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [np.stack([z, -v[..., 2], v[..., 1]], -1),
         np.stack([v[..., 2], z, -v[..., 0]], -1),
         np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _crossing_jacobian(xy: np.ndarray, tan_I: np.ndarray) -> np.ndarray:
    """d(crossing xy)/d(xi) for a right perturbation ``T_F_from_I @ exp(xi)``, xi = (omega, v).

    Shapes: xy (M, 2), tan_I (M, 3) -> (M, 2, 6). The curve moves by
    ``delta = P x omega - v`` in the image frame and the crossing slides
    along the tangent back to z = 0: ``dq = delta_xy - (t_xy / t_z) delta_z``.
    """
    x, y = xy[:, 0], xy[:, 1]
    tz = tan_I[:, 2]
    tz = np.where(np.abs(tz) < 1e-6, 1e-6, tz)
    a, b = tan_I[:, 0] / tz, tan_I[:, 1] / tz
    J = np.zeros((xy.shape[0], 2, 6))
    J[:, 0, 0], J[:, 0, 1], J[:, 0, 2], J[:, 0, 3], J[:, 0, 5] = a * y, -a * x, y, -1.0, a
    J[:, 1, 0], J[:, 1, 1], J[:, 1, 2], J[:, 1, 4], J[:, 1, 5] = b * y, -b * x, -x, -1.0, b
    return J


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """4x4 transform of a small twist xi = (omega (rad), v (mm)) (Rodrigues; v applied as is)."""
    wx, wy, wz, vx, vy, vz = (float(v) for v in xi)
    th2 = wx * wx + wy * wy + wz * wz
    th = math.sqrt(th2)
    if th < 1e-12:
        a, b = 1.0, 0.5
    else:
        a, b = math.sin(th) / th, (1 - math.cos(th)) / th2
    # I + a K + b K^2, K = [w]x, K^2 = w w^T - |w|^2 I
    return np.array([
        [1 + b * (wx * wx - th2), -a * wz + b * wx * wy, a * wy + b * wx * wz, vx],
        [a * wz + b * wx * wy, 1 + b * (wy * wy - th2), -a * wx + b * wy * wz, vy],
        [-a * wy + b * wx * wz, a * wx + b * wy * wz, 1 + b * (wz * wz - th2), vz],
        [0.0, 0.0, 0.0, 1.0]])


def _adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a rigid transform for twists (omega, v): [[R, 0], [[p]x R, R]]."""
    R, p = T[:3, :3], T[:3, 3]
    px, py, pz = (float(v) for v in p)
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = np.array([[0.0, -pz, py], [pz, 0.0, -px], [-py, px, 0.0]]) @ R
    return A


# --------------------------------------------------------------------------- refinement


@dataclass(frozen=True, eq=False)
class _Fit:
    """One refined joint hypothesis."""

    T_F_from_scanner: np.ndarray
    assignments: list  # per slice: (K,) int blob index or -1
    residuals: list  # per slice: (K,) mm, NaN where unassigned
    inside: list  # per slice: (K,) bool
    n_matched: int
    rms_mm: float
    # what the last fit was made of, when not the blob centroids: per slice (measured xy (N, 2) mm, square-root
    # information L (K, 2, 2) it was weighted by, the noise sigma L assumed) (see chic_register.uncertainty)
    measurements: list | None = None


def _assign(pred: np.ndarray, ok: np.ndarray, blobs_xy: np.ndarray, gate_mm: float) -> np.ndarray:
    """Blob index per tube (K,), -1 for none: minimum-cost matching within ``gate_mm``."""
    K = pred.shape[0]
    out = np.full(K, -1)
    if blobs_xy.shape[0] == 0 or not ok.any():
        return out
    diff = pred[:, None, :] - blobs_xy[None, :, :]
    d2 = np.einsum("ijk,ijk->ij", diff, diff)  # squared distances (K, N)
    within = (d2 < gate_mm * gate_mm) & ok[:, None]
    if within.sum(axis=0).max() <= 1 and within.sum(axis=1).max() <= 1:
        # every gated pair is alone in its row and column: they are the (unique) optimal matching
        r, c = np.nonzero(within)
        out[r] = c
        return out
    r, c = gated_matching(d2, within)
    out[r] = c
    return out


def refine(model: TubeModel, blobs_xy: list[np.ndarray], T_scanner_from_image: list[np.ndarray],
           T_F_from_scanner: np.ndarray, *, gates_mm=(3.0, 1.5, 1.0, 1.0), iters_per_gate: int = 3,
           final_iters: int = 4, damping: float = 1e-6, exclude: list | None = None,
           assign0: list | None = None, offsets_mm: list | None = None, strict_ends: bool = True,
           weights: list | None = None, tol: float = 1e-6) -> _Fit:
    """Gauss-Newton on all six DOF of ``T_F_from_scanner`` with re-assignment.

    ``blobs_xy``: per slice, detected centres in image mm (N_j, 2). Each gate
    in ``gates_mm`` re-solves the blob-tube assignment, then iterates; the
    final iterations keep the last assignment (``assign0``, per slice (K,)
    blob indices, when there are no gates). ``exclude``: per slice, a (K,)
    bool mask of tubes left unassigned (rejected outliers). ``offsets_mm``:
    per slice (K, 2), added to the predicted crossings (the centroid model:
    the centroid of a tube's image section minus its centreline crossing).
    ``strict_ends``: leave out crossings whose section a tube end cuts
    (their blob centre is biased) unless the offsets model that cut.
    ``weights``: per slice (K, 2, 2) or None, each tube's square-root
    information ``L`` (``L^T L`` = the inverse covariance of its measured
    position, mm^-2): the fit then minimises the sum of ``|L (predicted -
    measured)|^2`` (the maximum-likelihood pose for Gaussian position errors).
    ``tol``: the final iterations stop once a step is below it (rad and mm).
    """
    end_margin = 0.0 if strict_ends else 1e-9
    X = T_F_from_scanner.copy()
    ads = [_adjoint(invert(S)) for S in T_scanner_from_image]
    assign = list(assign0) if assign0 is not None else [None] * len(blobs_xy)
    offs = offsets_mm if offsets_mm is not None else [None] * len(blobs_xy)
    schedule = [(g, iters_per_gate) for g in gates_mm] + [(None, final_iters)]
    step = 1.0
    for gate, iters in schedule:
        changed = False
        for it in range(iters):
            if it == 1 and not changed and step < 1e-5:
                break  # converged and the assignment did not change
            Js, rs = [], []
            for j, (xy, S) in enumerate(zip(blobs_xy, T_scanner_from_image)):
                q, tan, _, inside = plane_crossings(model, X @ S, margin_mm=5.0 if gate is not None else end_margin)
                qm = q + offs[j] if offs[j] is not None else q  # what the detector measures
                if gate is not None and it == 0:
                    new = _assign(qm, inside & ~exclude[j] if exclude else inside, xy, gate)
                    changed = changed or assign[j] is None or not np.array_equal(new, assign[j])
                    assign[j] = new
                a = assign[j]
                k = np.flatnonzero((a >= 0) & inside)
                if k.size == 0:
                    continue
                res = qm[k] - xy[a[k]]
                Jk = _crossing_jacobian(q[k], tan[k]) @ ads[j]
                if weights is not None and weights[j] is not None:
                    L = weights[j][k]
                    res = np.einsum("kij,kj->ki", L, res)
                    Jk = np.einsum("kij,kjl->kil", L, Jk)
                rs.append(res.ravel())
                Js.append(Jk.reshape(-1, 6))
            if not rs:
                break
            J = Js[0] if len(Js) == 1 else np.concatenate(Js)
            r = rs[0] if len(rs) == 1 else np.concatenate(rs)
            H = J.T @ J
            diag = H.reshape(-1)[::7]  # a view of the diagonal
            diag *= 1 + damping
            diag += 1e-9
            try:
                xi = -np.linalg.solve(H, J.T @ r)
            except np.linalg.LinAlgError:
                break
            X = X @ _exp_se3(xi)
            step = float(np.abs(xi).max())
            # rad and mm: under a gate, close enough to re-assign; at the end, far below any error that matters
            if step < (1e-3 if gate is not None else tol):
                break
        if step > 1e-2:  # still wandering after a whole gate: a hopeless guess, give up
            break
    # final bookkeeping
    residuals, insides, total, sq = [], [], 0, 0.0
    for j, (xy, S) in enumerate(zip(blobs_xy, T_scanner_from_image)):
        q, _, _, inside = plane_crossings(model, X @ S, margin_mm=end_margin)
        if offs[j] is not None:
            q = q + offs[j]
        a = assign[j] if assign[j] is not None else np.full(model.is_helix.size, -1)
        a = np.where(inside, a, -1)
        assign[j] = a
        res = np.full(a.size, np.nan)
        k = np.flatnonzero(a >= 0)
        res[k] = np.linalg.norm(q[k] - xy[a[k]], axis=1)
        residuals.append(res)
        insides.append(inside)
        total += k.size
        sq += float(np.sum(res[k] ** 2))
    rms = math.sqrt(sq / total) if total else float("inf")
    return _Fit(X, assign, residuals, insides, total, rms)


def _section_extent(model, tan, slice_thickness_mm):
    """Each tube's in-plane section: half-length (mm) along its projected tangent ``u`` (K, 2), half-width across."""
    txy = np.hypot(tan[:, 0], tan[:, 1])
    tz = np.maximum(np.abs(tan[:, 2]), 1e-3)
    half_len = np.minimum(0.5 * model.diameter_mm / tz + 0.5 * slice_thickness_mm * txy / tz, model.length_mm)
    half_wid = 0.5 * model.diameter_mm + 0.5 * slice_thickness_mm
    u = tan[:, :2] / np.maximum(txy, 1e-12)[:, None]
    return half_len, half_wid, u


def centroid_offsets(tubes, model: TubeModel, T_F_from_I: np.ndarray, assignment: np.ndarray, footprints,
                     pixel_spacing_mm, slice_thickness_mm: float, *, supersample: int = 5,
                     thickness_samples: int = 5, purity: bool = False):
    """Where the detector sees each matched tube, relative to its centreline crossing; (K, 2) image mm.

    The centre the detector reports is the intensity centroid of the blob's
    footprint, not the centreline crossing: a helix's section is curved, a
    section is clipped by the tube's end and a neighbour can spill into the
    footprint. So each matched tube's footprint (``footprints[assignment[k]]``
    = (row0, col0, mask), from :class:`~chic_register.detect.Blobs`) is
    rendered noise-free at the pose ``T_F_from_I`` (4x4) with every tube
    (``tubes``, the geometry's objects) that reaches it, by the simulator's
    exact partial-volume renderer over the slice thickness; the offset is
    that footprint's centroid minus the crossing. Zero for unmatched tubes.
    Returns ``(offsets (K, 2), purity (K,))``; with ``purity=True`` that is
    the share of the tube's own signal inside its footprint times the share
    of the footprint's signal that is the tube's own (1: a clean blob; less:
    a touching neighbour or a footprint split through the section, whose
    centre follows the pose only weakly), else ones.
    """
    from .simulate import render_tubes

    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=5.0)
    K = q.shape[0]
    off = np.zeros((K, 2))
    pure = np.ones(K)
    rs, cs = (float(v) for v in pixel_spacing_mm)
    px = max(rs, cs)
    half_len, half_wid, u = _section_extent(model, tan, slice_thickness_mm)
    render = {"pixel_spacing_mm": (rs, cs), "slice_thickness_mm": slice_thickness_mm,
              "supersample": supersample, "thickness_samples": thickness_samples}
    for k in np.flatnonzero(assignment >= 0):
        r0, c0, mask = footprints[int(assignment[k])]
        h, w = mask.shape
        centre = np.array([(c0 + (w - 1) / 2) * cs, (r0 + (h - 1) / 2) * rs])
        half = 0.5 * math.hypot(h * rs, w * cs) + 2 * px
        d = centre - q
        along = np.abs(np.einsum("ij,ij->i", d, u))
        across = np.abs(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0])
        near = np.flatnonzero(found & (along < half + half_len) & (across < half + half_wid))
        near = np.union1d(near, [k])
        img = render_tubes([tubes[i] for i in near], T_F_from_I, (h, w), center_px=(-float(r0), -float(c0)),
                           **render)
        wgt = np.where(mask, img, 0.0)
        total = wgt.sum()
        if total <= 0:
            pure[k] = 0.0
            continue
        r = (wgt.sum(axis=1) @ np.arange(h)) / total + r0
        c = (wgt.sum(axis=0) @ np.arange(w)) / total + c0
        off[k] = (c * cs - q[k, 0], r * rs - q[k, 1])
        if purity:
            # the tube alone, in a window holding its whole section and the footprint
            ex = abs(u[k, 0]) * half_len[k] + abs(u[k, 1]) * half_wid[k] + 2 * px
            ey = abs(u[k, 1]) * half_len[k] + abs(u[k, 0]) * half_wid[k] + 2 * px
            R0 = min(r0, int(math.floor((q[k, 1] - ey) / rs)))
            C0 = min(c0, int(math.floor((q[k, 0] - ex) / cs)))
            R1 = max(r0 + h, int(math.ceil((q[k, 1] + ey) / rs)) + 1)
            C1 = max(c0 + w, int(math.ceil((q[k, 0] + ex) / cs)) + 1)
            own = render_tubes([tubes[k]], T_F_from_I, (R1 - R0, C1 - C0), center_px=(-float(R0), -float(C0)),
                               **render)
            own_total = own.sum()
            own_in = float(np.where(mask, own[r0 - R0:r0 - R0 + h, c0 - C0:c0 - C0 + w], 0.0).sum())
            pure[k] = (own_in / own_total) * (own_in / total) if own_total > 0 else 0.0
    return off, pure


def template_shifts(tubes, model: TubeModel, T_F_from_I: np.ndarray, assignment: np.ndarray, pixels: np.ndarray,
                    footprints, pixel_spacing_mm, slice_thickness_mm: float, *, supersample: int = 5,
                    thickness_samples: int = 5, grow_px: int = 2, step_px: float = 0.1):
    """Where each matched tube's section lies in the image by a template fit; (K, 2) image mm from its crossing.

    The centroid of a footprint sums the noise of every pixel in it; a
    matched filter uses only the section's edges and is about twice as
    precise in white noise. So for each matched tube, the noise-free image of
    its section at the pose ``T_F_from_I`` (4x4), rendered by the
    simulator's partial-volume renderer like :func:`centroid_offsets`, is
    fitted to ``pixels`` (rows, cols) over the blob's footprint grown by
    ``grow_px`` (less the other blobs' footprints):
    ``I = b + a (T(x - d) + N(x))``, N the neighbouring tubes at the pose,
    linear in (b, a, a d) once ``T(x - d)`` is expanded to first order (the
    derivative from renders shifted by ``+-step_px``). The shift is small
    near the converged pose, and the caller iterates at the refitted pose.
    Returns ``(shift (K, 2) mm, gain a (K,), fitted (K,) bool)``: the
    template's own position is the crossing plus ``shift`` (no centroid
    bias); ``fitted`` is False for unmatched tubes (gain 0), degenerate fits
    (gain NaN) and fits without a positive gain.
    """
    from .simulate import render_tubes

    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=5.0)
    K = q.shape[0]
    shift, gain, fitted = np.zeros((K, 2)), np.zeros(K), np.zeros(K, bool)
    rs, cs = (float(v) for v in pixel_spacing_mm)
    px = max(rs, cs)
    H, W = pixels.shape
    half_len, half_wid, u = _section_extent(model, tan, slice_thickness_mm)
    render = {"pixel_spacing_mm": (rs, cs), "slice_thickness_mm": slice_thickness_mm,
              "supersample": supersample, "thickness_samples": thickness_samples}
    g = int(grow_px)
    for k in np.flatnonzero(assignment >= 0):
        i = int(assignment[k])
        fr0, fc0, fmask = footprints[i]
        r0, c0 = max(0, fr0 - g), max(0, fc0 - g)
        r1, c1 = min(H, fr0 + fmask.shape[0] + g), min(W, fc0 + fmask.shape[1] + g)
        h, w = r1 - r0, c1 - c0
        own = np.zeros((h, w), bool)
        own[fr0 - r0:fr0 - r0 + fmask.shape[0], fc0 - c0:fc0 - c0 + fmask.shape[1]] = fmask
        mask = _dilate(own, g) if g > 0 else own.copy()
        for n, (or0, oc0, omask) in enumerate(footprints):
            if n == i or or0 >= r1 or oc0 >= c1 or or0 + omask.shape[0] <= r0 or oc0 + omask.shape[1] <= c0:
                continue
            a0, b0 = max(or0, r0), max(oc0, c0)
            a1, b1 = min(or0 + omask.shape[0], r1), min(oc0 + omask.shape[1], c1)
            other = omask[a0 - or0:a1 - or0, b0 - oc0:b1 - oc0]
            sub = mask[a0 - r0:a1 - r0, b0 - c0:b1 - c0]
            sub &= ~(other & ~own[a0 - r0:a1 - r0, b0 - c0:b1 - c0])
        centre = np.array([(c0 + (w - 1) / 2) * cs, (r0 + (h - 1) / 2) * rs])
        half = 0.5 * math.hypot(h * rs, w * cs) + 2 * px
        d = centre - q
        along = np.abs(np.einsum("ij,ij->i", d, u))
        across = np.abs(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0])
        near = [n for n in np.flatnonzero(found & (along < half + half_len) & (across < half + half_wid)) if n != k]

        def draw(tube_list, dr_px=0.0, dc_px=0.0):
            # the section moved by (dr, dc) pixels: the grid's origin moves the other way
            return render_tubes(tube_list, T_F_from_I, (h, w), center_px=(-float(r0) + dr_px, -float(c0) + dc_px),
                                **render)

        # composited as the image is: the brighter of the tube and its neighbours (touching sections overlap)
        # (forward differences: a derivative a little off costs a little precision, never bias, since the
        # residual vanishes at the true pose whatever the derivative)
        nbr = draw([tubes[n] for n in near]) if near else np.zeros((h, w))
        tpl = np.maximum(draw([tubes[k]]), nbr)
        dT_dr = (np.maximum(draw([tubes[k]], step_px), nbr) - tpl) / step_px
        dT_dc = (np.maximum(draw([tubes[k]], 0.0, step_px), nbr) - tpl) / step_px
        m = mask.ravel()
        A = np.stack([np.ones(int(m.sum())), tpl.ravel()[m], dT_dr.ravel()[m], dT_dc.ravel()[m]], axis=1)
        y = np.asarray(pixels[r0:r1, c0:c1], float).ravel()[m]
        try:
            coef, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
        except np.linalg.LinAlgError:
            continue
        gain[k] = coef[1] if rank == 4 else math.nan
        if not gain[k] > 0:
            continue
        # first order: a T(x - d) = a T(x) + (a d) . dT/dd
        shift[k] = (coef[3] / coef[1] * cs, coef[2] / coef[1] * rs)
        fitted[k] = True
    return shift, gain, fitted


def _centroid_refine(model: TubeModel, tubes, fit: _Fit, xys, Ss, slices, blob_sets, opts) -> _Fit:
    """Refit ``fit`` with the centroid model (:func:`centroid_offsets`).

    A fixed-point iteration: offsets at the current pose, refit, repeated
    until the pose moves less than 1e-4 (mm and rad) or ``centroid_iterations``
    times. Tubes whose blob is not clean (purity below
    ``centroid_min_purity``: a touching neighbour, a footprint split through
    the section) are left out while enough tubes remain: their centre
    follows the pose only weakly, which the fixed point follows slowly,
    and a split's boundary moves with the noise.
    """
    assign = [a.copy() for a in fit.assignments]
    for it in range(opts.centroid_iterations):
        X0 = fit.T_F_from_scanner
        offs = []
        for j, (sl, S, b) in enumerate(zip(slices, Ss, blob_sets)):
            off, pure = centroid_offsets(
                tubes, model, fit.T_F_from_scanner @ S, assign[j], b.footprints, sl.pixel_spacing_mm,
                float(sl.slice_thickness_mm), supersample=opts.centroid_supersample,
                thickness_samples=opts.centroid_thickness_samples, purity=it == 0)
            offs.append(off)
            if it == 0:
                for k in np.argsort(pure):
                    if pure[k] >= opts.centroid_min_purity:
                        break
                    n_all = sum(int((a >= 0).sum()) for a in assign)
                    n_depth = sum(int(((a >= 0) & model.depth_coding).sum()) for a in assign)
                    if n_all <= opts.min_tubes or (model.depth_coding[k] and n_depth <= opts.min_depth_tubes):
                        continue
                    assign[j][k] = -1
        fit = refine(model, xys, Ss, fit.T_F_from_scanner, gates_mm=(), final_iters=6, assign0=assign,
                     offsets_mm=offs, strict_ends=False)
        d = invert(X0) @ fit.T_F_from_scanner
        if max(abs(d[:3, 3]).max(), abs(d[:3, :3] - np.eye(3)).max()) < 1e-4:
            break
    if opts.template_iterations > 0:
        fit = _template_refine(model, tubes, fit, assign, xys, Ss, slices, blob_sets, opts, offs)
    return fit


def _template_refine(model: TubeModel, tubes, fit: _Fit, assign, xys, Ss, slices, blob_sets, opts,
                     centroid_offs) -> _Fit:
    """Refit ``fit`` on template-fitted tube positions (:func:`template_shifts`), ``template_iterations`` times.

    Each matched tube's measurement becomes the position of its fitted
    template (crossing plus shift, offset zero); a tube whose template fit
    is degenerate keeps its centroid and centroid-model offset. Raises
    :class:`NoLock` when a template lands more than ``template_max_disagreement_px``
    from where the centroid model puts the tube, or fits with no positive
    gain: the blob is not the clean section the model expects.
    """
    for it in range(opts.template_iterations):
        X0 = fit.T_F_from_scanner
        new_xys, offs = [], []
        for j, (sl, S, b) in enumerate(zip(slices, Ss, blob_sets)):
            T_F_from_I = fit.T_F_from_scanner @ S
            a = assign[j]
            render = {"supersample": opts.centroid_supersample, "thickness_samples": opts.centroid_thickness_samples}
            thick = float(sl.slice_thickness_mm)
            shift, gain, ok = template_shifts(tubes, model, T_F_from_I, a, np.asarray(sl.pixels), b.footprints,
                                              sl.pixel_spacing_mm, thick, **render)
            matched = a >= 0
            if np.any(matched & (gain <= 0)):  # (NaN, a degenerate fit, keeps the centroid instead)
                k = int(np.flatnonzero(matched & (gain <= 0))[0])
                raise NoLock(f"{sl.source}: tube {model.ids[k]} matches a blob its template does not fit "
                             f"(gain {gain[k]:.3g})", {"n_tubes": int(matched.sum())})
            rest = np.where(ok, -1, a)
            if it == 0:  # the centroid model's last offsets (the pose has barely moved since)
                off = centroid_offs[j].copy()
            elif np.any(rest >= 0):
                off = centroid_offsets(tubes, model, T_F_from_I, rest, b.footprints, sl.pixel_spacing_mm, thick,
                                       **render)[0]
            else:
                off = np.zeros((a.size, 2))
            q = plane_crossings(model, T_F_from_I, margin_mm=5.0)[0]
            kk = np.flatnonzero(ok)
            xy = xys[j].copy()
            if it == 0 and kk.size:
                gap = np.linalg.norm(xy[a[kk]] - off[kk] - (q[kk] + shift[kk]), axis=1)
                limit = opts.template_max_disagreement_px * _pixel_mm(sl)
                if gap.max() > limit:
                    k = int(kk[np.argmax(gap)])
                    raise NoLock(f"{sl.source}: tube {model.ids[k]}'s template fit is {gap.max():.3f} mm from its "
                                 f"centroid fit (limit {opts.template_max_disagreement_px:g} px)",
                                 {"n_tubes": int(matched.sum())})
            xy[a[kk]] = q[kk] + shift[kk]
            off[kk] = 0.0
            new_xys.append(xy)
            offs.append(off)
        fit = refine(model, new_xys, Ss, fit.T_F_from_scanner, gates_mm=(), final_iters=6, assign0=assign,
                     offsets_mm=offs, strict_ends=False)
        d = invert(X0) @ fit.T_F_from_scanner
        if max(abs(d[:3, 3]).max(), abs(d[:3, :3] - np.eye(3)).max()) < 1e-5:
            break
    return fit


def _section_refine(model: TubeModel, fit: _Fit, xys, Ss, slices, blob_sets, opts) -> _Fit | None:
    """Refit ``fit`` on section-fitted tube positions (:func:`~chic_register.section.fit_sections`).

    Up to ``section_iterations`` passes: fit every matched tube's section
    model at the current pose, then refit the pose on the fitted positions,
    each weighted by its information matrix. A tube whose section cannot be fitted
    (window too small, no positive gain) is left out, and so is one whose
    fitted section lies more than ``section_max_shift_px`` from where the
    pose predicts it or has less than half the median gain (not the clean
    section the model expects). Fewer than ``min_tubes`` clean sections
    (tubes in tissue, blobs much wider than the channels) return ``None``:
    the blob-centre pose then stands, and is verified like any other.
    """
    from .section import fit_sections

    assign = [a.copy() for a in fit.assignments]
    wins = [None] * len(slices)  # each tube's pixels: chosen at the first pass, kept (the pose barely moves)
    px = min(_pixel_mm(sl) for sl in slices)
    exact = True
    for it in range(opts.section_iterations):
        X0 = fit.T_F_from_scanner
        new_xys, Ls, q_before = [], [], []
        # a pass far from the fit's fixed point only has to bring the next one close: a coarser model (3 planes,
        # straight edges) and one Gauss-Newton step of the pose do for it; exact passes repeat until one moves
        # the tube crossings by less than section_done_px (its first-order fit is then exact to ~1e-3 px)
        for j, (sl, S, b) in enumerate(zip(slices, Ss, blob_sets)):
            a = assign[j]
            sf, wins[j] = fit_sections(model, X0 @ S, a, np.asarray(sl.pixels), sl.pixel_spacing_mm,
                                       float(sl.slice_thickness_mm), b.noise_sigma, footprints=b.footprints,
                                       thickness_samples=(opts.section_thickness_samples if exact
                                                          else min(3, opts.section_thickness_samples)),
                                       windows=wins[j], exact=exact)
            q_before.append(sf.predicted_mm)
            ok = sf.fitted.copy()
            if ok.any():  # a section far from where the locked pose puts it, or faint, is not the tube's
                shift = np.linalg.norm(sf.position_mm - sf.predicted_mm, axis=1)
                ok &= (shift <= opts.section_max_shift_px * _pixel_mm(sl)) & (sf.gain >= 0.5 * median(sf.gain[ok]))
            a[(a >= 0) & ~ok] = -1
            k = np.flatnonzero(a >= 0)
            xy = xys[j].copy()
            xy[a[k]] = sf.position_mm[k]
            new_xys.append(xy)
            L = np.zeros_like(sf.info)
            L[k] = np.swapaxes(np.linalg.cholesky(sf.info[k]), 1, 2)
            Ls.append(L)
        n_all = sum(int((a >= 0).sum()) for a in assign)
        if n_all < opts.min_tubes:
            return None
        fit = refine(model, new_xys, Ss, X0, gates_mm=(), final_iters=6 if exact else 1, assign0=assign,
                     strict_ends=False, weights=Ls, tol=1e-5)  # (1e-5 rad, mm: far below the noise)
        fit = dataclasses.replace(fit, measurements=[(xy, L, float(b.noise_sigma))
                                                     for xy, L, b in zip(new_xys, Ls, blob_sets)])
        moved = 0.0  # how far the matched tubes' crossings moved in this pass (mm)
        for j, S in enumerate(Ss):
            k = np.flatnonzero(assign[j] >= 0)
            q0 = q_before[j][k]
            q1 = plane_crossings(model, fit.T_F_from_scanner @ S, margin_mm=1e-9)[0][k]
            moved = max(moved, float(np.max(np.linalg.norm(q1 - q0, axis=1), initial=0.0)))
        if exact and moved < opts.section_done_px * px:
            break
        exact = moved < opts.section_close_px * px
    return fit


# --------------------------------------------------------------------------- public API


@dataclass(frozen=True)
class SliceResult:
    """The registered pose of one slice relative to the fiducial.

    ``residuals_mm`` and ``assignment`` are keyed by tube id (matched tubes
    only); ``blobs_rc`` (N, 2) are all detected candidate centres (row, col),
    ``predicted_rc`` {tube id: (row, col)} the model's crossings, ``ellipse``
    the fitted ellipse of tube centres in image mm (or None).
    """

    source: str
    depth_mm: float
    tilt_deg: float
    azimuth_deg: float
    twist_deg: float
    residual_rms_mm: float
    residuals_mm: dict
    n_tubes: int
    assignment: dict
    blobs_rc: np.ndarray = field(repr=False, default=None)
    predicted_rc: dict = field(repr=False, default=None)
    ellipse: Ellipse | None = field(repr=False, default=None)
    missing_tubes: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        return {
            **({"missing_tubes": list(self.missing_tubes)} if self.missing_tubes else {}),
            "source": self.source,
            "depth_mm": round(self.depth_mm, 6),
            "tilt_deg": round(self.tilt_deg, 6),
            "azimuth_deg": round(self.azimuth_deg, 6),
            "twist_deg": round(self.twist_deg, 6),
            "residual_rms_mm": round(self.residual_rms_mm, 6),
            "n_tubes": self.n_tubes,
            "residuals_mm": {k: round(v, 6) for k, v in self.residuals_mm.items()},
            "assignment": dict(self.assignment),
        }


@dataclass(frozen=True)
class SkippedSlice:
    """A slice left out of a joint registration: why, and (for one that disagrees) its residual under the pose."""

    source: str
    reason: str
    residual_rms_mm: float | None = None

    def to_dict(self) -> dict:
        out = {"source": self.source, "reason": self.reason}
        if self.residual_rms_mm is not None:
            out["residual_rms_mm"] = round(self.residual_rms_mm, 6)
        return out


@dataclass(frozen=True)
class Registration:
    """A trusted pose: ``T_scanner_from_fiducial`` (4x4, mm) and one :class:`SliceResult` per slice."""

    status: str
    T_scanner_from_fiducial: np.ndarray
    slices: tuple[SliceResult, ...]
    timing_ms: dict
    geometry_name: str = ""
    geometry_sha256: str = ""
    skipped: tuple = ()
    uncertainty: object = field(repr=False, default=None)  # chic_register.uncertainty.PoseUncertainty

    def to_dict(self) -> dict:
        """JSON-ready object, CONTRACT.md section 4 plus extra keys (``covariance``, ``noise``,
        ``target_F_mm``, ``predicted_tre_mm``: :meth:`~chic_register.uncertainty.PoseUncertainty.to_dict`)."""
        return {
            "status": self.status,
            "T_scanner_from_fiducial": [[float(v) for v in row] for row in self.T_scanner_from_fiducial],
            "slices": [s.to_dict() for s in self.slices],
            "n_slices_used": len(self.slices),
            "skipped_slices": [s.to_dict() for s in self.skipped],
            "timing_ms": {k: round(v, 3) for k, v in self.timing_ms.items()},
            "geometry": {"name": self.geometry_name, "sha256": self.geometry_sha256},
            **(self.uncertainty.to_dict() if self.uncertainty is not None else {}),
        }


@dataclass(frozen=True)
class SolveOptions:
    """Trust thresholds and search settings of :func:`register`.

    ``max_rms_px``: largest accepted RMS residual, in pixels of each slice;
    ``max_residual_px``: largest accepted single-tube residual; ``min_tubes``
    and ``min_depth_tubes``: fewest matched tubes in all, and of tubes not
    parallel to the axis (helices), needed for a lock; ``ambiguity_ratio``:
    a distinct second pose matching as many tubes with an RMS within this
    factor of the best makes the fit ambiguous (a pose that leaves a tube
    unexplained loses: near-symmetric layouts always have one that fits all
    but one tube). ``centroid_model``: after the lock, refit predicting
    each tube's section centroid as the detector measures it, not its
    centreline crossing (:func:`centroid_offsets`; removes the bias of
    curved, clipped and touching sections at a few ms per iteration:
    ``centroid_iterations`` renders of every matched tube's footprint with
    ``centroid_supersample``² samples per pixel and
    ``centroid_thickness_samples`` sub-planes). Then, ``template_iterations``
    times, each clean tube's position is measured by fitting its rendered
    section to the pixels (:func:`template_shifts`; about 1.5 times more
    precise than a centroid in white noise) and the pose refitted on those;
    a template landing more than ``template_max_disagreement_px`` from the
    centroid model's position gives :class:`NoLock`. 0 turns it off.
    ``section_fit`` (the default mode, unless ``centroid_model``): after the
    lock, each matched tube's section is located by fitting an analytic
    model of it to its pixels (:mod:`chic_register.section`, with
    ``section_thickness_samples`` planes across the slice) and the pose is
    refitted on those positions, weighted by their information; up to
    ``section_iterations`` passes (see :func:`_section_refine`); tubes whose
    fit lands more than ``section_max_shift_px`` from the pose's prediction
    are left out. Off: the pose fitted to blob centroids (faster, biased).
    ``verify``: before ``ok``, prove the pose against the image
    (:mod:`chic_register.verify_pose`: envelope, every predicted section
    present with its shape, nothing unexplained on the tubes' circle, pixel
    spacing, no rival that explains the pixels nearly as well, and a
    predicted error (3 sigma) within ``trust_tre_mm`` at the frame centre and
    ``trust_rot_deg``; when only that last test fails in the fast mode and
    ``refine_when_imprecise``, the accuracy mode's refinement is tried before
    refusing); off only for
    studies of the raw fit.
    ``uncertainty``: compute the pose's covariance and predicted TRE
    (:mod:`~chic_register.uncertainty`; a few ms per slice; always when
    ``max_tre_mm`` is finite); ``max_tre_mm``: a pose whose predicted TRE at
    the registration's target exceeds it gives :class:`NoLock` (``imprecise``).
    ``prior``: an approximate ``T_scanner_from_fiducial`` (4x4, only its
    rotation is used): poses turned more than ``prior_max_deg`` from it are
    never considered. It is what resolves a geometry that maps onto itself
    under a rotation (the classic Z-frame does, under a half turn): without
    it, such a fit is refused as ambiguous.
    """

    max_rms_px: float = 0.5
    max_residual_px: float = 1.5
    min_tubes: int = 6
    min_depth_tubes: int = 2
    ambiguity_ratio: float = 3.0
    max_hypotheses: int = 4
    max_tilt_deg: float = 75.0
    centroid_model: bool = False
    centroid_iterations: int = 4
    centroid_supersample: int = 5
    centroid_thickness_samples: int = 5
    centroid_min_purity: float = 0.93
    template_iterations: int = 1
    template_max_disagreement_px: float = 0.5
    section_fit: bool = True
    section_iterations: int = 5
    section_close_px: float = 0.2
    section_done_px: float = 0.05
    section_thickness_samples: int = 5
    section_max_shift_px: float = 1.0
    verify: bool = True
    trust_tre_mm: float = 1.0
    trust_rot_deg: float = 0.75
    refine_when_imprecise: bool = False
    max_tre_mm: float = math.inf
    uncertainty: bool = True
    prior: np.ndarray | None = None
    prior_max_deg: float = 60.0


def _pixel_mm(sl: Slice) -> float:
    return float(max(sl.pixel_spacing_mm))


def _to_xy_mm(blobs: Blobs, sl: Slice) -> np.ndarray:
    rc = blobs.centres_rc
    return np.stack([rc[:, 1] * sl.pixel_spacing_mm[1], rc[:, 0] * sl.pixel_spacing_mm[0]], axis=1)


def _distinct(T1: np.ndarray, T2: np.ndarray, model: TubeModel) -> bool:
    """Two fiducial poses differ by more than 1 mm at any tube end or by more than 1 degree."""
    dR = T1[:3, :3].T @ T2[:3, :3]
    ang = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dR) - 1) / 2))))
    L = model.length_mm
    rmax = float(np.max(model.axis_radius_mm)) if model.axis_radius_mm.size else 0.0
    pts = np.array([[rmax, 0, 0], [-rmax, 0, L], [0, rmax, L / 2], [0, 0, 0], [0, 0, L]])
    a = pts @ T1[:3, :3].T + T1[:3, 3]
    b = pts @ T2[:3, :3].T + T2[:3, 3]
    return ang > 1.0 or float(np.max(np.linalg.norm(a - b, axis=1))) > 1.0


def _rotation_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (degrees) of the rotation between two 3x3 rotations."""
    return math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(R1.T @ R2)) - 1) / 2))))


def _near_prior(T_F_from_scanner: np.ndarray, opts: "SolveOptions") -> bool:
    """True without a prior, else when the pose's rotation lies within ``prior_max_deg`` of the prior's."""
    if opts.prior is None:
        return True
    R_prior = np.asarray(opts.prior, float)[:3, :3]  # R_scanner_from_fiducial
    return _rotation_deg(T_F_from_scanner[:3, :3].T, R_prior) <= opts.prior_max_deg


def _depth_tube_name(model: TubeModel) -> str:
    """What the tubes that tell the depth are, by their shape: 'helical', 'diagonal' or 'depth-coding' (both)."""
    kinds = {"helical" if model.is_helix[k] else "diagonal" for k in np.flatnonzero(model.depth_coding)}
    return kinds.pop() if len(kinds) == 1 else "depth-coding"


def _solve_one(model: TubeModel, xy: np.ndarray, S: np.ndarray, opts: SolveOptions, pixel_mm: float):
    """Refined hypotheses of one slice, best first, and the ellipse (or None). Raises NoLock if there are none.

    First guesses come from the paper's closed form when the layout allows it
    (:func:`~chic_register.hypotheses.ellipse_layout`), else, or when that
    yields no acceptable fit, from the generic stage
    (:func:`~chic_register.hypotheses.family_hypotheses`). Every guess gets a
    short refinement; the best, and any distinct rival as good as it, are then
    refined to convergence. With a prior orientation (``opts.prior``), guesses
    and fits farther from it are dropped.
    """
    if xy.shape[0] < opts.min_tubes:
        raise NoLock(f"found {xy.shape[0]} candidate tube cross-sections; need at least {opts.min_tubes}",
                     {"n_candidates": int(xy.shape[0])})
    gate = max(float(model.diameter_mm.max()), 2 * pixel_mm)
    limit = opts.max_rms_px * pixel_mm
    fits, ell = [], None
    if ellipse_layout(model):
        radius = median(model.axis_radius_mm)
        ell_fit = fit_ellipse_robust(xy, radius, max_tilt_deg=opts.max_tilt_deg,
                                     tol_mm=max(0.08 * radius, 1.5 * pixel_mm))
        if ell_fit is not None:
            ell, inl = ell_fit
            hyps = initial_hypotheses(model, xy[inl], ell, max_hypotheses=opts.max_hypotheses)
            fits = _refine_guesses(model, xy, S, hyps, opts, pixel_mm, gate)
    if not fits or fits[0].n_matched < opts.min_tubes or fits[0].rms_mm > limit:
        if parallel_family(model) is None:
            if not fits:
                raise NoLock("the geometry has no family of three parallel straight tubes that are not in one "
                             "plane, which the generic first guess needs, and no ellipse of tube centres "
                             "was found", {"n_candidates": int(xy.shape[0])})
        else:
            hyps = family_hypotheses(model, xy, gate_mm=gate, max_tilt_deg=opts.max_tilt_deg,
                                     max_hypotheses=6 * opts.max_hypotheses)
            extra = _refine_guesses(model, xy, S, hyps, opts, pixel_mm, gate)
            if ell is not None or ellipse_layout(model):
                # a fallback where the closed form applies but found nothing: only a fit that explains
                # (nearly) every tube it puts in the slice, as the closed form's fits would
                extra = [f for f in extra if _unexplained(f) <= 1]
            fits = _rank(fits + extra, limit)
    if not fits:
        raise NoLock("the detected centres do not match the geometry's tube pattern",
                     {"n_candidates": int(xy.shape[0])})
    return fits, ell


def _unexplained(fit: _Fit) -> int:
    """Tubes a fit puts wholly inside the slice (every slice) that no blob is assigned to."""
    return sum(int(np.sum(ins & (a < 0))) for ins, a in zip(fit.inside, fit.assignments))


def _refine_guesses(model: TubeModel, xy: np.ndarray, S: np.ndarray, hyps: list, opts: SolveOptions,
                    pixel_mm: float, gate: float) -> list:
    """Rank first guesses ``T_F_from_I`` by the tubes they line up, refine the best; fits best first."""
    S_inv = invert(S)
    # rank the guesses by how many tubes they line up before refining any
    scored = []
    for T in hyps:
        X = T @ S_inv
        if not _near_prior(X, opts):
            continue
        q, _, _, inside = plane_crossings(model, T, margin_mm=5.0)
        scored.append((int((_assign(q, inside, xy, gate) >= 0).sum()), X))
    scored.sort(key=lambda t: -t[0])

    def full(X):
        return refine(model, [xy], [S], X, gates_mm=(2 * gate, 0.6 * gate), iters_per_gate=3, final_iters=2)

    # refine in order until a fit explains at least as many tubes as any guess
    # still untried lines up; those rivals (for the ambiguity check) get a short
    # refinement first and a full one only if they come close
    fits = []
    limit = opts.max_rms_px * pixel_mm
    for count, X in scored:
        if fits and count < fits[0].n_matched and fits[0].rms_mm <= limit:
            break
        if fits:
            quick = refine(model, [xy], [S], X, gates_mm=(gate,), iters_per_gate=2, final_iters=0)
            if (quick.n_matched < fits[0].n_matched or quick.rms_mm > 2 * limit
                    or not _distinct(quick.T_F_from_scanner, fits[0].T_F_from_scanner, model)):
                fits.append(quick)
                continue
        fit = _reject_outliers(model, [xy], [S], full(X), [pixel_mm], opts)
        if _near_prior(fit.T_F_from_scanner, opts):
            fits = _rank(fits + [fit], limit)
    return fits


def _reject_outliers(model: TubeModel, xys, Ss, fit: _Fit, px_mm: list[float], opts: SolveOptions) -> _Fit:
    """Drop the worst-fitting tube while that makes the fit markedly better, and refit.

    Tried while the worst residual exceeds ``max_rms_px`` pixels (two
    touching tubes, a bubble, a blob merged with anatomy); a drop is kept
    when the RMS falls by at least a third. Never below ``min_tubes`` /
    ``min_depth_tubes``.
    """
    K = len(model.ids)
    excl = [np.zeros(K, bool) for _ in xys]
    gate = max(float(model.diameter_mm.max()), 2 * max(px_mm))
    for _ in range(max(0, fit.n_matched - opts.min_tubes)):
        res = [np.where(np.isfinite(r), r / px, -1.0) for r, px in zip(fit.residuals, px_mm)]
        j = int(np.argmax([r.max() for r in res]))
        k = int(np.argmax(res[j]))
        if res[j][k] <= opts.max_rms_px:
            break
        n_depth = sum(int(np.sum((a >= 0) & model.depth_coding)) for a in fit.assignments)
        if model.depth_coding[k] and n_depth <= opts.min_depth_tubes:
            break
        trial_excl = [e.copy() for e in excl]
        trial_excl[j][k] = True
        trial = refine(model, xys, Ss, fit.T_F_from_scanner, gates_mm=(0.6 * gate,), iters_per_gate=4,
                       final_iters=2, exclude=trial_excl)
        if trial.n_matched < fit.n_matched - 1 or trial.rms_mm > fit.rms_mm / 1.5:
            break
        fit, excl = trial, trial_excl
    return fit


def _rank(fits: list[_Fit], rms_limit_mm: float = math.inf) -> list[_Fit]:
    """Best first: fits within the RMS limit, then the most tubes, then the lowest RMS."""
    return sorted(fits, key=lambda f: (f.rms_mm > rms_limit_mm, -f.n_matched, f.rms_mm))


def _check_trust(fit: _Fit, others: list[_Fit], model: TubeModel, slices: list[Slice], opts: SolveOptions,
                 Ss: list | None = None, res_mm: list | None = None):
    """Raise :class:`NoLock` unless ``fit`` is a trustworthy pose.

    ``Ss``: the slices' T_scanner_from_image; ``res_mm``: the unit of each
    slice's thresholds (:func:`_resolution_mm`; default its pixel).
    """
    n_depth = 0
    px_unit = res_mm if res_mm is not None else [_pixel_mm(sl) for sl in slices]
    for j, sl in enumerate(slices):
        a = fit.assignments[j]
        px = px_unit[j]
        res = fit.residuals[j][a >= 0]
        n_depth += int(np.sum((a >= 0) & model.depth_coding))
        if res.size and math.sqrt(float(np.mean(res**2))) > opts.max_rms_px * px:
            raise NoLock(
                f"{sl.source}: residual RMS {math.sqrt(float(np.mean(res ** 2))):.3f} mm exceeds "
                f"{opts.max_rms_px:g} px ({opts.max_rms_px * px:.3f} mm"
                + (")" if px == _pixel_mm(sl) else f", counting the image's resolution of {px:.2f} mm as a pixel)"),
                {"residual_rms_mm": round(math.sqrt(float(np.mean(res**2))), 4)})
        if res.size and res.max() > opts.max_residual_px * px:
            raise NoLock(f"{sl.source}: a tube residual of {res.max():.3f} mm exceeds "
                         f"{opts.max_residual_px:g} px", {"max_residual_mm": round(float(res.max()), 4)})
        T_F_from_I = fit.T_F_from_scanner @ (Ss[j] if Ss is not None else sl.T_scanner_from_image())
        ang = slice_angles(T_F_from_I)
        if not (0.0 <= ang.depth_mm <= model.length_mm):
            raise NoLock(f"{sl.source}: the slice crosses the fiducial axis at depth {ang.depth_mm:.1f} mm, "
                         f"outside the body [0, {model.length_mm:g}] mm",
                         {"depth_mm": round(float(ang.depth_mm), 3)})
    need_depth = min(opts.min_depth_tubes, int(model.depth_coding.sum()))
    if fit.n_matched < opts.min_tubes or n_depth < need_depth:
        name = _depth_tube_name(model)
        raise NoLock(f"only {fit.n_matched} tubes matched ({n_depth} {name}); need at least "
                     f"{opts.min_tubes} with {need_depth} {name}", {"n_tubes": fit.n_matched})
    for other in others:
        if (other.n_matched >= fit.n_matched and other.n_matched >= opts.min_tubes
                and other.rms_mm <= opts.ambiguity_ratio * max(fit.rms_mm, 1e-3)
                and other.rms_mm <= opts.max_rms_px * min(px_unit)
                and _distinct(fit.T_F_from_scanner, other.T_F_from_scanner, model)):
            hint = "" if opts.prior is not None else "; an approximate orientation (prior, --prior) picks one"
            raise NoLock(f"ambiguous fit: two distinct poses match {fit.n_matched} and {other.n_matched} "
                         f"tubes with RMS {fit.rms_mm:.3f} and {other.rms_mm:.3f} mm{hint}",
                         {"n_tubes": fit.n_matched})


def _resolution_mm(sl: Slice, blobs: Blobs) -> float:
    """The unit of a slice's trust thresholds (mm): what its image can resolve, never less than a pixel.

    A centre is as precise as the blob is sharp: blobs wider than the tube
    (blur, partial volume, fluid around a printed channel; ``blobs.width_mm``
    measured in the image) and thick slices (a tilted tube's section is
    smeared over the thickness) both widen the error, so the unit is the
    largest of the pixel, a 7.5th of the blob width and a 6th of the slice
    thickness (equal to the pixel for 3 mm tubes at 0.5 mm pixels and 2-3 mm slices).
    """
    w = blobs.width_mm if math.isfinite(blobs.width_mm) else 0.0
    return max(_pixel_mm(sl), w / 7.5, float(sl.slice_thickness_mm) / 6.0)


def _track(model: TubeModel, xy: np.ndarray, S: np.ndarray, T_F_from_scanner: np.ndarray, sl: Slice,
           opts: SolveOptions, res_mm: float):
    """A slice's fit refined from a pose found in another slice of the same volume, if trustworthy; else None."""
    gate = max(float(model.diameter_mm.max()), 2 * res_mm)
    fit = refine(model, [xy], [S], T_F_from_scanner, gates_mm=(gate, 0.6 * gate), iters_per_gate=3, final_iters=2)
    fit = _reject_outliers(model, [xy], [S], fit, [res_mm], opts)
    try:
        _check_trust(fit, [], model, [sl], opts, [S], [res_mm])
    except NoLock:
        return None
    return fit


def register(slices: list[Slice], geom: FiducialGeometry, *, options: SolveOptions | None = None,
             detect_options: dict | None = None, skip_failed: bool = False, target_F_mm=None,
             **overrides) -> Registration:
    """Register one or more slices of the fiducial: one ``T_scanner_from_fiducial`` from all.

    Each slice is detected and solved on its own, then all correspondences
    are refined jointly. By default every slice must lock; with
    ``skip_failed`` (a volume's slices, most of which may miss the fiducial)
    slices that do not lock are skipped, later slices are first tried from
    the pose already found (tracking), and a slice that disagrees with the
    joint pose is dropped; each is listed in ``Registration.skipped`` with
    its reason. ``overrides`` set fields of :class:`SolveOptions` (e.g.
    ``max_rms_px=0.4``); ``detect_options`` go to
    :func:`~chic_register.detect.detect_blobs`. ``target_F_mm``: the
    point of F whose predicted TRE is reported (default: the geometry's tool
    tip, else the body's centre on its axis). Raises :class:`NoLock` with a
    reason when no trustworthy pose exists.
    """
    opts = dataclasses.replace(options or SolveOptions(), **overrides)
    if not slices:
        raise NoLock("no slices given")
    t0 = time.perf_counter()
    model, geom_sha = prepare_geometry(geom)
    blob_sets, xys = [], []
    for sl in slices:
        b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm, **(detect_options or {}))
        blob_sets.append(b)
        xys.append(_to_xy_mm(b, sl))
    t1 = time.perf_counter()
    Ss = [sl.T_scanner_from_image() for sl in slices]
    res_mm = [_resolution_mm(sl, b) for sl, b in zip(slices, blob_sets)]
    per_slice = [None] * len(slices)
    rivals = [[] for _ in slices]  # per slice: the distinct fits that came close (for the verification)
    skipped = []
    anchor = None
    for j in _solve_order(xys, model, skip_failed):
        sl, xy, S = slices[j], xys[j], Ss[j]
        if anchor is not None:
            fit = _track(model, xy, S, anchor, sl, opts, res_mm[j])
            if fit is not None:
                per_slice[j] = (fit, None)
                continue
        try:
            try:
                fits, ell = _solve_one(model, xy, S, opts, res_mm[j])
                _check_trust(fits[0], fits[1:], model, [sl], opts, [S], [res_mm[j]])
            except NoLock as first:
                if (detect_options or {}).get("flatten_background") or not _worth_flattening(blob_sets[j], model):
                    raise
                # tissue touching the tubes or a dim side of the image: once more on the flattened image
                b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm, flatten_background=True,
                                 **(detect_options or {}))
                xy2, res2 = _to_xy_mm(b, sl), _resolution_mm(sl, b)
                try:
                    fits, ell = _solve_one(model, xy2, S, opts, res2)
                    _check_trust(fits[0], fits[1:], model, [sl], opts, [S], [res2])
                    if _unexplained(fits[0]) > 1:  # a second look is held to explaining (nearly) every tube
                        raise NoLock("more than one predicted tube unexplained on the flattened image")
                except NoLock:
                    raise first from None  # the plain image's reason says more
                xy = xys[j] = xy2
                blob_sets[j], res_mm[j] = b, res2
        except NoLock as exc:
            reason = exc.reason if exc.reason.startswith(f"{sl.source}: ") else f"{sl.source}: {exc.reason}"
            if skip_failed:
                skipped.append((j, SkippedSlice(sl.source, reason[len(sl.source) + 2:])))
                continue
            if len(slices) > 1:
                raise NoLock(reason, exc.detail) from None
            raise
        per_slice[j] = (fits[0], ell)
        rivals[j] = fits[1:]
        if skip_failed and anchor is None:
            anchor = fits[0].T_F_from_scanner
    skipped = [s for _, s in sorted(skipped, key=lambda js: js[0])]  # in the slices' order
    used = [j for j in range(len(slices)) if per_slice[j] is not None]
    if not used:
        raise NoLock(_no_slice_locked(skipped), {"n_skipped": len(skipped)})
    slices, xys, Ss, blob_sets, res_mm, per_slice, rivals = (
        [seq[j] for j in used] for seq in (slices, xys, Ss, blob_sets, res_mm, per_slice, rivals))
    if len(slices) == 1:
        best = per_slice[0][0]
    else:
        best, dropped = _joint(model, slices, xys, Ss, res_mm, per_slice, opts, skip_failed)
        if dropped:
            skipped += [SkippedSlice(slices[j].source, why, rms) for j, why, rms in dropped]
            keep = [j for j in range(len(slices)) if j not in {d[0] for d in dropped}]  # the fit's slices, in order
            slices, xys, Ss, blob_sets, res_mm, per_slice, rivals = (
                [seq[j] for j in keep] for seq in (slices, xys, Ss, blob_sets, res_mm, per_slice, rivals))
    locked = best  # the pose fitted to the blob centres
    if opts.section_fit and not opts.centroid_model:
        fine = _section_refine(model, best, xys, Ss, slices, blob_sets, opts)
        if fine is not None:
            _check_trust(fine, [], model, slices, opts, Ss, res_mm)
            if _distinct(fine.T_F_from_scanner, best.T_F_from_scanner, model):
                raise NoLock("the section fit moved the pose by more than 1 mm or 1 degree: the fit is not stable",
                             {"n_tubes": fine.n_matched})
            best = fine
    if opts.centroid_model:
        corrected = _centroid_refine(model, geom.tubes, best, xys, Ss, slices, blob_sets, opts)
        _check_trust(corrected, [], model, slices, opts, Ss)  # only ever stricter: the lock was checked above
        if _distinct(corrected.T_F_from_scanner, best.T_F_from_scanner, model):
            raise NoLock("the centroid model moved the pose by more than 1 mm or 1 degree: the fit is not stable",
                         {"n_tubes": corrected.n_matched})
        best = corrected
    checks = None
    if opts.verify:  # the last word: the pose proved against the pixels (chic_register.verify_pose)
        from .verify_pose import verify_fit

        try:
            checks = verify_fit(geom, model, best, rivals, slices, Ss, blob_sets, opts)
        except ImprecisePose:
            if opts.centroid_model or not opts.refine_when_imprecise:
                raise
            checks = None
            if best is not locked:
                # the precision test estimates the noise from the residual scatter, unweighted: the section fit's
                # residuals along elongated sections make it pessimistic, so the centroid fit is judged as it is
                # without the section fit (never a refusal the centroid-only solver would not make)
                try:
                    checks = verify_fit(geom, model, locked, rivals, slices, Ss, blob_sets, opts)
                    best = locked
                except ImprecisePose:
                    pass
        if checks is None:
            # verified but not precise enough from the centroids: fit the sections themselves (the accuracy
            # mode), then decide on that
            accurate = _centroid_refine(model, geom.tubes, locked, xys, Ss, slices, blob_sets, opts)
            _check_trust(accurate, [], model, slices, opts, Ss)
            if _distinct(accurate.T_F_from_scanner, best.T_F_from_scanner, model):
                raise NoLock("the accuracy refinement moved the pose by more than 1 mm or 1 degree: the fit is "
                             "not stable", {"n_tubes": accurate.n_matched}) from None
            best = accurate
            checks = verify_fit(geom, model, best, rivals, slices, Ss, blob_sets, opts)
    t2 = time.perf_counter()
    T_sf = invert(best.T_F_from_scanner)
    results = []
    for j, (sl, S) in enumerate(zip(slices, Ss)):
        T_F_from_I = best.T_F_from_scanner @ S
        ang = slice_angles(T_F_from_I)
        a = best.assignments[j]
        q, _, _, inside = plane_crossings(model, T_F_from_I)
        k = np.flatnonzero(a >= 0)
        res = best.residuals[j]
        px = sl.pixel_spacing_mm
        results.append(SliceResult(
            source=sl.source, depth_mm=float(ang.depth_mm), tilt_deg=float(ang.tilt_deg),
            azimuth_deg=float(ang.azimuth_deg), twist_deg=float(ang.twist_deg),
            residual_rms_mm=float(math.sqrt(np.mean(res[k] ** 2))),
            residuals_mm={model.ids[i]: float(res[i]) for i in k},
            n_tubes=int(k.size),
            assignment={model.ids[i]: int(a[i]) for i in k},
            blobs_rc=blob_sets[j].centres_rc,
            predicted_rc={model.ids[i]: (float(q[i, 1] / px[0]), float(q[i, 0] / px[1]))
                          for i in np.flatnonzero(inside)},
            ellipse=per_slice[j][1],
            missing_tubes=checks[j].missing if checks else (),
        ))
    t3 = time.perf_counter()
    unc = None
    if opts.uncertainty or math.isfinite(opts.max_tre_mm):
        from .uncertainty import registration_uncertainty, target_point

        unc = registration_uncertainty(model, best, xys, Ss, slices, blob_sets, target_point(geom, target_F_mm),
                                       "centroid" if not opts.centroid_model else "template (centroid covariance)")
        if unc.predicted_tre_mm > opts.max_tre_mm:
            raise NoLock(f"imprecise: predicted TRE {unc.predicted_tre_mm:.3f} mm at "
                         f"({', '.join(f'{v:g}' for v in unc.target_F_mm)}) exceeds {opts.max_tre_mm:g} mm",
                         {"code": "imprecise", "predicted_tre_mm": round(unc.predicted_tre_mm, 4),
                          "max_tre_mm": opts.max_tre_mm})
    t4 = time.perf_counter()
    timing = {"detect": (t1 - t0) * 1e3, "pose": (t2 - t1) * 1e3, "uncertainty": (t4 - t3) * 1e3,
              "total": (t4 - t0) * 1e3}
    return Registration("ok", T_sf, tuple(results), timing, geom.name, geom_sha, tuple(skipped), unc)


def _worth_flattening(blobs: Blobs, model: TubeModel) -> bool:
    """A slice whose detection may have lost tubes to their surroundings: something bright, but not a blank image."""
    bright = blobs.threshold - blobs.background > 4 * blobs.noise_sigma  # Otsu split more than noise
    return math.isfinite(blobs.threshold) and blobs.noise_sigma > 0 and bright and len(blobs) < 3 * len(model.ids)


def _solve_order(xys: list, model: TubeModel, skip_failed: bool) -> list[int]:
    """The order slices are solved in: as given, or (skipping) those with about one blob per tube first."""
    if not skip_failed:
        return list(range(len(xys)))
    K = len(model.ids)
    return sorted(range(len(xys)), key=lambda j: (abs(xys[j].shape[0] - K), j))


def _no_slice_locked(skipped: list) -> str:
    """One line for slices of which none locked: how many, the commonest reasons, and one in full."""
    import re

    groups: dict[str, list] = {}
    for s in skipped:
        key = re.sub(r"\d+(\.\d+)?", "N", s.reason.split(":")[0]).strip()
        groups.setdefault(key, []).append(s)
    common = sorted(groups.items(), key=lambda kv: -len(kv[1]))
    head = common[0][1][len(common[0][1]) // 2]
    return (f"no slice of {len(skipped)} locked (" + "; ".join(f"{len(v)}x {k}" for k, v in common[:3])
            + f"); e.g. {head.source}: {head.reason}")


def _joint(model: TubeModel, slices, xys, Ss, res_mm, per_slice, opts: SolveOptions, skip_failed: bool):
    """The joint fit of every slice's correspondences; ``(fit, dropped)``.

    Without ``skip_failed`` any disagreement is :class:`NoLock`. With it, a
    slice whose residual under the joint pose breaks its trust thresholds, or
    that matches fewer tubes than it did alone, is dropped (the worst first,
    then refit) and returned in ``dropped`` as ``(index, reason, RMS mm)``;
    ``fit`` then covers the remaining slices, in their order.
    """
    start = min(per_slice, key=lambda fe: fe[0].rms_mm)[0].T_F_from_scanner
    active = list(range(len(slices)))
    dropped = []
    while True:
        gate = max(model.diameter_mm.max(), 2 * max(res_mm[j] for j in active))
        sub = [xys[j] for j in active], [Ss[j] for j in active]
        best = refine(model, sub[0], sub[1], start, gates_mm=(gate, 0.6 * gate))
        if not skip_failed:
            _check_trust(best, [], model, slices, opts, Ss, res_mm)
            if best.n_matched < sum(f.n_matched for f, _ in per_slice):
                raise NoLock("the slices disagree: the joint pose matches fewer tubes than the slices alone",
                             {"n_tubes": best.n_matched})
            return best, dropped
        worst, why, worst_score = None, "", 1.0
        for n, j in enumerate(active):
            a, r = best.assignments[n], best.residuals[n]
            rms = math.sqrt(float(np.mean(r[a >= 0] ** 2))) if (a >= 0).any() else math.inf
            score = rms / (opts.max_rms_px * res_mm[j])
            if (a >= 0).sum() < per_slice[j][0].n_matched:
                score, reason = max(score, 1.0 + 1e-9) + 10.0, (
                    f"disagrees with the other slices: {int((a >= 0).sum())} tubes matched under the joint pose, "
                    f"{per_slice[j][0].n_matched} alone")
            else:
                reason = (f"disagrees with the other slices: residual RMS {rms:.3f} mm under the joint pose "
                          f"(limit {opts.max_rms_px * res_mm[j]:.3f} mm)")
            if score > worst_score:
                worst, why, worst_score = n, reason, score
        if worst is None or len(active) == 1:
            _check_trust(best, [], model, [slices[j] for j in active], opts, [Ss[j] for j in active],
                         [res_mm[j] for j in active])
            return best, dropped
        j = active[worst]
        own = per_slice[j][0].assignments[0]  # the slice's own correspondences, at the joint pose
        q = plane_crossings(model, best.T_F_from_scanner @ Ss[j], margin_mm=5.0)[0]
        k = np.flatnonzero(own >= 0)
        rms = math.sqrt(float(np.mean(np.sum((q[k] - xys[j][own[k]]) ** 2, axis=1)))) if k.size else float("nan")
        if "tubes matched" in why:
            why += f"; its own tubes are {rms:.3f} mm RMS from the joint pose's crossings"
        dropped.append((j, why, rms))
        active.pop(worst)
        start = best.T_F_from_scanner
