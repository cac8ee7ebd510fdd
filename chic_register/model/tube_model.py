"""The solver's tube model: the geometry file's centrelines as arrays, and where they cross an image plane.

:class:`TubeModel` holds every tube of a :class:`~chic_register.model.geometry.FiducialGeometry`
in arrays so that :func:`plane_crossings` predicts all crossings of a pose
at once; :func:`crossing_jacobian`, :func:`exp_se3` and :func:`adjoint`
are the pose derivatives the refinement (:mod:`chic_register.fit.refine`), the
verification and the uncertainty need; :func:`section_extent` is the size
of a tube's section in a slab. Kept free of the solver's search so that the
verification, the section fit and the uncertainty use the same model.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from chic_register.model.geometry import FiducialGeometry, content_sha256
from chic_register.model.pose import invert
from chic_register.model.tubes import HelixTube, LineTube


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
    probe_points_mm: np.ndarray = None  # (5, 3) points of F two poses are compared at (trust._distinct)
    line_dd: np.ndarray = None  # the line tubes' d . d
    line_length_mm: np.ndarray = None  # and |d|
    flat_rise_mm: tuple = ()  # per tube: a line rising less than this in z (its diameter) is tested by its parameter
    strict_terms: tuple = ()  # per tube (half diameter, z_lo, z_hi) as floats (plane_crossings' strict extent test)
    crossing_memo: dict = None  # plane_crossings' memo: pose bytes -> _crossings' result
    crossing_template: tuple = ()  # _crossings' flat slots and tangent z with the line tubes' constants
    extent_bounds: dict = None  # margin (mm) -> the widened extent (z_lo - margin - 1e-6, z_hi + margin + 1e-6)

    def __post_init__(self):
        L = self.length_mm
        rmax = float(np.max(self.axis_radius_mm)) if self.axis_radius_mm.size else 0.0
        probes = np.array([[rmax, 0, 0], [-rmax, 0, L], [0, rmax, L / 2], [0, 0, 0], [0, 0, L]])  # tube, axis ends
        probes.flags.writeable = False
        object.__setattr__(self, "probe_points_mm", probes)
        li, hi = np.flatnonzero(~self.is_helix), np.flatnonzero(self.is_helix)
        d = self.d[li]
        object.__setattr__(self, "line_idx", li)
        object.__setattr__(self, "helix_idx", hi)
        object.__setattr__(self, "line_p0", self.p0[li].copy())
        object.__setattr__(self, "line_d", d.copy())
        object.__setattr__(self, "line_dunit", d / np.linalg.norm(d, axis=1, keepdims=True))
        object.__setattr__(self, "line_dd", np.einsum("ij,ij->i", d, d))
        object.__setattr__(self, "line_length_mm", np.linalg.norm(d, axis=1))
        object.__setattr__(self, "flat_rise_mm", tuple(self.diameter_mm.tolist()))
        object.__setattr__(self, "strict_terms", tuple(zip(
            (0.5 * self.diameter_mm).tolist(), self.z_lo.tolist(), self.z_hi.tolist())))
        object.__setattr__(self, "crossing_memo", {})
        object.__setattr__(self, "extent_bounds", {})
        object.__setattr__(self, "line_params", tuple(
            (int(k), 6 * int(k), *(float(v) for v in self.p0[k]), *(float(v) for v in self.d[k])) for k in li))
        object.__setattr__(self, "helix_params", tuple(
            (int(k), 6 * int(k), float(self.radius[k]), float(self.theta0_rad[k]),
             float(self.omega_rad_per_mm[k]), float(self.z0[k])) for k in hi))
        # _crossings' per-tube slots [crossing (3), unit tangent (3)] with the line tubes' constant tangents filled in
        flat, tan_z = [0.0] * (6 * len(self.ids)), [0.0] * len(self.ids)
        for k in li:
            flat[6 * k + 3:6 * k + 6] = (self.d[k] / np.linalg.norm(self.d[k])).tolist()
            tan_z[k] = flat[6 * k + 5]
        object.__setattr__(self, "crossing_template", (tuple(flat), tuple(tan_z)))

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
            if t.curved:  # a helix (the Tube protocol's only curved kind)
                is_helix[k] = True
                radius[k], th0[k] = t.radius, math.radians(t.theta0_deg)
                om[k], z0[k] = math.radians(t.pitch_deg_per_mm), t.z0
                rad_axis[k] = t.radius
            else:
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


class GeometryKey:
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
        self.key = (geom.name, geom.units, repr(geom.body), tubes_repr(geom.tubes), frozen_src)
        self._hash = hash(self.key)

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other) -> bool:
        return isinstance(other, GeometryKey) and self.key == other.key


#: id of a geometry's tube tuple -> (the tuple, its repr): the tuple is held, so its id stays its own; only tubes
#: of immutable values (:func:`immutable_tubes`), whose repr cannot change
TUBES_REPR: dict = {}


def tubes_repr(tubes) -> str:
    """``repr(tubes)``, memoised per tuple of immutable tubes (~25 us each time for nine tubes; the solver keys
    its memos on it on every call)."""
    hit = TUBES_REPR.get(id(tubes))
    if hit is not None and hit[0] is tubes:
        return hit[1]
    text = repr(tubes)
    if immutable_tubes(tubes):
        if len(TUBES_REPR) >= 16:
            TUBES_REPR.clear()
        TUBES_REPR[id(tubes)] = (tubes, text)
    return text


def immutable_tubes(tubes) -> bool:
    """Whether ``tubes`` is a tuple of the frozen tube classes holding only str, bool, int, float and tuples of
    floats (nothing a caller could change in place)."""
    if type(tubes) is not tuple:
        return False
    for t in tubes:
        if type(t) not in (LineTube, HelixTube):
            return False
        for v in (getattr(t, name) for name in t.__dataclass_fields__):
            if type(v) is tuple:
                if not all(type(x) in (float, int) for x in v):
                    return False
            elif type(v) not in (str, bool, int, float):
                return False
    return True


@functools.lru_cache(maxsize=8)
def _prepared(key: GeometryKey) -> tuple[TubeModel, str]:
    """The tube model and the content hash of a geometry, computed once per distinct geometry."""
    return TubeModel.from_geometry(key.geom), content_sha256(key.geom.content())


def prepare_geometry(geom: FiducialGeometry) -> tuple[TubeModel, str]:
    """``(TubeModel, content sha256)`` of ``geom``, memoised on its content (repeat calls cost ~10 us)."""
    try:
        return _prepared(GeometryKey(geom))
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
    hit = crossings_memo(model, np.asarray(T_F_from_I, dtype=float))
    return hit[0][:, :2].copy(), hit[1].copy(), np.array(hit[2]), inside_mask(model, hit, margin_mm)


def crossings_memo(model: TubeModel, T_F_from_I: np.ndarray):
    """:func:`_crossings` of a float64 (4, 4) pose, memoised per model (read-only arrays: views, not copies, for
    the refinement's inner loop). The solver asks for the same pose's crossings several times (a fit, then its
    checks)."""
    key = T_F_from_I.tobytes()
    memo = model.crossing_memo
    hit = memo.get(key)
    if hit is None:
        hit = _crossings(model, T_F_from_I)
        if len(memo) >= 64:  # a solve's first guesses and their refinements fit (a few kB each)
            memo.clear()
        memo[key] = hit
    return hit


def inside_mask(model: TubeModel, hit: tuple, margin_mm: float) -> np.ndarray:
    """:func:`plane_crossings`' ``inside`` (K,) bool of a :func:`_crossings` result (a new array)."""
    return np.array(inside_list(model, hit, margin_mm), dtype=bool)


def inside_list(model: TubeModel, hit: tuple, margin_mm: float) -> list:
    """:func:`inside_mask` as a list of K bools.

    Scalar code over the tubes (numpy's own arithmetic and comparisons, the same numbers): a dozen array
    operations on nine tubes cost several times more.
    """
    _, tan_I, zF, found, tan_z, _ = hit
    if margin_mm > 0:
        bounds = model.extent_bounds.get(margin_mm)
        if bounds is None:  # the same numbers each time: computed once per margin (a few margins in use)
            if len(model.extent_bounds) >= 16:
                model.extent_bounds.clear()
            bounds = model.extent_bounds[margin_mm] = tuple(zip(
                (model.z_lo - margin_mm - 1e-6).tolist(), (model.z_hi + margin_mm + 1e-6).tolist()))
        return [ok and lo <= z <= hi for ok, z, (lo, hi) in zip(found, zF, bounds)]
    # strict: the whole cross-section must lie within the tube, else the blob is cut short by the
    # tube's end and its centre is biased: half the cut's length along the tube, in z of F
    out = []
    for ok, z, tz_I, tz_F, (half_d, z_lo, z_hi) in zip(found, zF, tan_I[:, 2].tolist(), tan_z, model.strict_terms):
        cos_a = max(abs(tz_I), 1e-6)
        clear = half_d * math.sqrt(max(1 - cos_a * cos_a, 0.0)) / cos_a * abs(tz_F)
        out.append(ok and z >= z_lo + clear - 1e-6 and z <= z_hi - clear + 1e-6)
    return out


def _crossings(model: TubeModel, T_F_from_I: np.ndarray):
    """:func:`plane_crossings` before the extent test: ``(q (K, 3), tan_I (K, 3), z_F, found, tangent z in F, qt)``:
    z_F, found and the tangent's z lists of K floats (bools); ``qt`` (K, 2, 3) the array q and tan_I are views of."""
    (_, _, nx, ox), (_, _, ny, oy), (_, _, nz, oz) = T_F_from_I[:3].tolist()
    no = nx * ox + ny * oy + nz * oz  # the plane: x . n = no
    K = len(model.ids)
    # per tube k, in F: flat[6k:6k+6] = crossing less the image origin, unit tangent (a line's: in the template)
    flat, tan_z = list(model.crossing_template[0]), list(model.crossing_template[1])
    zF, found = [0.0] * K, [False] * K
    for k, k6, px, py, pz, dx, dy, dz in model.line_params:
        denom = dx * nx + dy * ny + dz * nz
        safe = abs(denom) > 1e-9
        t = (no - (px * nx + py * ny + pz * nz)) / (denom if safe else 1.0)
        z = pz + t * dz
        flat[k6:k6 + 3] = (px + t * dx - ox, py + t * dy - oy, z - oz)
        zF[k] = z
        # a line that barely rises in z (an N-localizer's edge rods, across the box): its z range cannot tell
        # whether the plane meets it, its own parameter does (0..1 from p0 to p1)
        found[k] = safe and (abs(dz) >= model.flat_rise_mm[k] or -1e-9 <= t <= 1.0 + 1e-9)
    if model.helix_params:
        z_axis = no / nz if abs(nz) > 1e-9 else 0.0
        cos, sin = math.cos, math.sin
        for k, k6, r, th0, om, z0 in model.helix_params:
            z = z_axis
            rnx, rny = r * nx, r * ny
            good = False
            for _ in range(30):
                th = th0 + om * (z - z0)
                c, s = cos(th), sin(th)
                dg = om * (rny * c - rnx * s) + nz
                if -1e-9 < dg < 1e-9:
                    dg = 1e-9
                step = (rnx * c + rny * s + nz * z - no) / dg
                if step > 20.0:
                    step = 20.0
                elif step < -20.0:
                    step = -20.0
                z -= step
                if -1e-11 < step < 1e-11:
                    good = True
                    break
            th = th0 + om * (z - z0)
            c, s = cos(th), sin(th)
            vx, vy = -r * om * s, r * om * c
            inv = 1.0 / math.sqrt(vx * vx + vy * vy + 1.0)
            flat[k6:k6 + 6] = (r * c - ox, r * s - oy, z - oz, vx * inv, vy * inv, inv)
            zF[k], found[k], tan_z[k] = z, good and abs(rnx * c + rny * s + nz * z - no) < 1e-6, inv
    # rows R^T (X - o) and R^T tan in one product: (K, 2, 3), the crossing then the tangent of each tube
    qt = (np.fromiter(flat, float, 6 * K).reshape(2 * K, 3) @ T_F_from_I[:3, :3]).reshape(K, 2, 3)
    return qt[:, 0], qt[:, 1], zF, found, tan_z, qt


def section_extent(model, tan, slice_thickness_mm):
    """Each tube's in-plane section: half-length (mm) along its projected tangent ``u`` (K, 2), half-width across."""
    txy = np.hypot(tan[:, 0], tan[:, 1])
    tz = np.maximum(np.abs(tan[:, 2]), 1e-3)
    half_len = np.minimum(0.5 * model.diameter_mm / tz + 0.5 * slice_thickness_mm * txy / tz, model.length_mm)
    half_wid = 0.5 * model.diameter_mm + 0.5 * slice_thickness_mm
    u = tan[:, :2] / np.maximum(txy, 1e-12)[:, None]
    return half_len, half_wid, u


def section_box(half_len: np.ndarray, half_wid: np.ndarray, u: np.ndarray):
    """``(ex, ey)`` (K,): half-extents along the image's x and y of each section's box (``half_len`` along its
    in-plane direction ``u`` (K, 2), ``half_wid`` across it)."""
    ax, ay = np.abs(u[:, 0]), np.abs(u[:, 1])
    return ax * half_len + ay * half_wid, ay * half_len + ax * half_wid


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices of vectors (..., 3) -> (..., 3, 3)."""
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [np.stack([z, -v[..., 2], v[..., 1]], -1),
         np.stack([v[..., 2], z, -v[..., 0]], -1),
         np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def crossing_jacobian(xy: np.ndarray, tan_I: np.ndarray) -> np.ndarray:
    """d(crossing xy)/d(xi) for a right perturbation ``T_F_from_I @ exp(xi)``, xi = (omega, v).

    Shapes: xy (M, 2), tan_I (M, 3) -> (M, 2, 6). The curve moves by
    ``delta = P x omega - v`` in the image frame and the crossing slides
    along the tangent back to z = 0: ``dq = delta_xy - (t_xy / t_z) delta_z``.
    """
    x, y = xy[:, 0:1], xy[:, 1]
    tz = tan_I[:, 2:3]
    ab = tan_I[:, :2] / np.where(np.abs(tz) < 1e-6, 1e-6, tz)  # (M, 2): a, b
    J = np.zeros((xy.shape[0], 2, 6))
    np.multiply(ab, y[:, None], out=J[:, :, 0])  # a y, b y
    np.multiply(-ab, x, out=J[:, :, 1])  # -a x, -b x
    J[:, 0, 2], J[:, 1, 2] = y, -x[:, 0]
    J[:, 0, 3] = J[:, 1, 4] = -1.0
    J[:, :, 5] = ab
    return J


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """4x4 transform of a small twist xi = (omega (rad), v (mm)) (Rodrigues; v applied as is)."""
    wx, wy, wz, vx, vy, vz = map(float, xi)
    th2 = wx * wx + wy * wy + wz * wz
    th = math.sqrt(th2)
    if th < 1e-12:
        a, b = 1.0, 0.5
    else:
        a, b = math.sin(th) / th, (1 - math.cos(th)) / th2
    # I + a K + b K^2, K = [w]x, K^2 = w w^T - |w|^2 I (one flat tuple to numpy: cheaper than nested lists)
    return np.fromiter((
        1 + b * (wx * wx - th2), -a * wz + b * wx * wy, a * wy + b * wx * wz, vx,
        a * wz + b * wx * wy, 1 + b * (wy * wy - th2), -a * wx + b * wy * wz, vy,
        -a * wy + b * wx * wz, a * wx + b * wy * wz, 1 + b * (wz * wz - th2), vz,
        0.0, 0.0, 0.0, 1.0), float, 16).reshape(4, 4)


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a rigid transform for twists (omega, v): [[R, 0], [[p]x R, R]]."""
    R, p = T[:3, :3], T[:3, 3]
    px, py, pz = (float(v) for v in p)
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    A[3:, :3] = np.array([[0.0, -pz, py], [pz, 0.0, -px], [-py, px, 0.0]]) @ R
    return A


def poses_distinct(X1: np.ndarray, X2: np.ndarray, model: TubeModel, mm: float = 1.0, deg: float = 1.0) -> bool:
    """Two poses (``T_F_from_scanner``) put some tube end of the fiducial more than ``mm`` apart in the scanner, or
    differ by more than ``deg`` in rotation (1 mm, 1 degree). Measured in F (``X1 X2^-1`` moves each point of F to
    where the second pose puts it, as the first sees it), so a frame far from the scanner's origin is judged by its
    own size, not by its distance from the isocentre."""
    D = X1 @ invert(X2)
    dR = D[:3, :3]
    ang = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dR) - 1) / 2))))
    if ang > deg:
        return True
    pts = model.probe_points_mm  # tube ends on the axis circle, the axis ends
    d = pts @ dR.T + D[:3, 3] - pts
    return float(np.sqrt(np.add.reduce(d * d, axis=1)).max()) > mm  # (np.linalg.norm's formula, less its checks)
