"""The image's scale fitted with the pose: along the image's columns and rows, and across a volume's slices.

Real images are a few tenths of a per cent larger or smaller than the
scanner says (gradient calibration is good to 1-2 %), and so are prints
(0.1-0.5 %). A rigid pose absorbs part of such a scale as a tilt and leaves
the rest in the residuals. :func:`fit_scale` extends the fit, at its
assignments and weights, by one relative scale per axis about the fiducial's
centre: ``x`` (the image columns) and ``y`` (the rows) for any slices, and
``z`` (the spacing of parallel slices, a volume's) when the slices lie at
different depths. The scale's covariance comes from the same normal
equations; its effect on the pose (the pose block of the joint covariance
less the rigid one) widens the pose's covariance where the pose takes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.detect.detected import DetectedSlice
from chic_register.fit.checks import gamma_p
from chic_register.fit.refine import Fit, refine, scanner_crossing_jacobian
from chic_register.model.pose import invert
from chic_register.model.pose_params import deg_mm_scale
from chic_register.model.tube_model import TubeModel, adjoint, exp_se3, plane_crossings

#: Axis names of :attr:`ScaleFit.scale`.
AXES = ("x", "y", "z")
#: Gauss-Newton steps of the joint fit (it starts at the rigid solution; the model is linear in the scale).
ITERATIONS = 3


@dataclass(frozen=True)
class ScaleFit:
    """The pose fitted together with the image's scale.

    ``T_F_from_scanner``: the pose so fitted (:func:`scaled_fit` makes it a fit);
    ``scale`` (n,): per axis of ``axes``, the relative correction of the
    image's spacing that registers it rigidly (``+0.006``: the pixel
    spacing along that axis reads 0.6 % too small, or the fiducial is 0.6 %
    smaller than its geometry file says); ``scale_sd`` (n,): their standard
    deviations; ``p``: the tail probability of the F test that the scale
    explains nothing (a small ``p``: the data show a scale);
    ``pose_covariance`` (6, 6): what the scale's uncertainty adds to the
    pose's covariance, in F's parameters (deg, mm: the order of
    :data:`~chic_register.model.pose_params.PARAMETER_ORDER`);
    ``unfitted_covariance`` (6, 6): what an unmeasured in-plane scale of
    unit standard deviation per image axis (a print, a scanner's
    calibration) puts in the rigid pose's covariance, ``B B^T`` with ``B``
    the least-squares pose's move per unit scale (times ``sd^2`` for a
    scale of SD ``sd``).
    """

    T_F_from_scanner: np.ndarray
    axes: tuple[str, ...]
    scale: np.ndarray
    scale_sd: np.ndarray
    p: float
    pose_covariance: np.ndarray
    unfitted_covariance: np.ndarray

    def to_dict(self) -> dict:
        return {"axes": list(self.axes), "scale": [round(float(v), 6) for v in self.scale],
                "sd": [round(float(v), 6) for v in self.scale_sd], "p": float(self.p)}


def _rows(model: TubeModel, fit: Fit, seen: list[DetectedSlice], X: np.ndarray, s: np.ndarray, centre: np.ndarray,
          with_z: bool):
    """Whitened residuals (M,), pose Jacobian (M, 6) and scale Jacobian (M, n) at pose ``X`` and scale ``s``."""
    meas = fit.measurements
    n = 3 if with_z else 2
    rs, Jp, Js = [], [], []
    for j, d in enumerate(seen):
        S = d.T_scanner_from_image
        q, tan, _, inside = plane_crossings(model, X @ S, margin_mm=1e-9)
        a = fit.assignments[j]
        k = np.flatnonzero((a >= 0) & inside)
        if k.size == 0:
            continue
        xy = np.asarray(meas[j][0] if meas is not None else d.xy_mm, float)[a[k]]
        L = meas[j][1][k] if meas is not None else np.broadcast_to(np.eye(2), (k.size, 2, 2))
        c = (invert(S) @ np.append(centre, 1.0))[:3]  # the fiducial's centre in this slice's image frame
        depth = -c[2]  # how far the slice lies from the centre along its normal (mm)
        D = np.zeros((k.size, 2, n))
        D[:, 0, 0], D[:, 1, 1] = -(xy[:, 0] - c[0]), -(xy[:, 1] - c[1])  # d(q - c - (1 + s)(xy - c)) / ds
        t = tan[k]
        if with_z:  # the slice further from the centre by s_z depth: its crossings move along the tubes
            D[:, :, 2] = depth * t[:, :2] / t[:, 2:3]
        r = q[k] - xy + np.einsum("kij,j->ki", D, s)
        J = scanner_crossing_jacobian(q[k], t, S)
        Jp.append(np.einsum("kij,kjl->kil", L, J).reshape(-1, 6))
        Js.append(np.einsum("kij,kjl->kil", L, D).reshape(-1, n))
        rs.append(np.einsum("kij,kj->ki", L, r).ravel())
    if not rs:
        return None
    return np.concatenate(rs), np.concatenate(Jp), np.concatenate(Js)


def fit_scale(model: TubeModel, fit: Fit, seen: list[DetectedSlice], sigma_mm: float | None = None) -> ScaleFit | None:
    """``fit`` refitted with the image's scale (:class:`ScaleFit`); None when too few residuals remain.

    ``sigma_mm``: the positions' noise when ``fit`` was fitted to unweighted
    blob centres (default: from the residuals); a fit weighted by its
    measurements' information (``fit.measurements``) is already whitened.
    The through-plane scale is fitted only when the slices are parallel and
    lie at least a channel's width apart in depth.
    """
    X0 = fit.T_F_from_scanner
    centre = (invert(X0) @ np.array([0.0, 0.0, 0.5 * model.length_mm, 1.0]))[:3]  # scanner mm
    normals = np.array([d.T_scanner_from_image[:3, 2] for d in seen])
    depths = [float(normals[0] @ d.T_scanner_from_image[:3, 3]) for d in seen]
    with_z = (len(seen) > 1 and bool(np.all(np.abs(normals @ normals[0]) > 1 - 1e-6))
              and max(depths) - min(depths) >= float(model.diameter_mm.max()))
    n = 3 if with_z else 2
    X, s = X0.copy(), np.zeros(n)
    rows = _rows(model, fit, seen, X, s, centre, with_z)
    if rows is None or rows[0].size - 6 - n <= 0:
        return None
    r, Jp, Js = rows
    dof = r.size - 6 - n
    r_rigid = float(r @ r)
    B = np.linalg.lstsq(Jp, Js[:, :2], rcond=None)[0]  # (6, 2): the rigid pose's move per unit in-plane scale
    unfitted = _to_F_parameters(B @ B.T, X0)
    for _ in range(ITERATIONS):
        J = np.hstack([Jp, Js])
        step = np.linalg.lstsq(J, r, rcond=None)[0]
        X = X @ exp_se3([-v for v in step[:6]])
        s = s - step[6:]
        rows = _rows(model, fit, seen, X, s, centre, with_z)
        if rows is None or rows[0].size != r.size:  # a tube left the slices: the rigid fit stands
            return None
        r, Jp, Js = rows
        if max(abs(step[:6]).max(), abs(step[6:]).max()) < 1e-9:
            break
    rss = float(r @ r)
    var = rss / dof if (fit.measurements is None and sigma_mm is None) else max(rss / dof, 1.0)
    if fit.measurements is None and sigma_mm is not None:
        var = max(rss / dof, sigma_mm ** 2)
    J = np.hstack([Jp, Js])
    C = var * np.linalg.pinv(J.T @ J)
    C_rigid = var * np.linalg.pinv(Jp.T @ Jp)
    F = ((r_rigid - rss) / n) / (rss / dof) if rss > 0 else math.inf
    p = _f_tail(F, n, dof)
    extra = _to_F_parameters(C[:6, :6] - C_rigid, X)
    return ScaleFit(X, AXES[:n], s, np.sqrt(np.maximum(np.diag(C)[6:], 0.0)), p, extra, unfitted)


def scaled_fit(model: TubeModel, fit: Fit, seen: list[DetectedSlice], sf: ScaleFit) -> Fit:
    """``fit`` moved to the pose fitted with the scale (``sf``): its residuals at that pose, its assignments and
    measurements kept."""
    refit = refine(model, [d.xy_mm for d in seen], [d.T_scanner_from_image for d in seen], sf.T_F_from_scanner,
                   gates_mm=(), final_iters=0, assign0=[a.copy() for a in fit.assignments])
    return Fit(sf.T_F_from_scanner, refit.assignments, refit.residuals, refit.inside, refit.n_matched, refit.rms_mm,
               fit.measurements)


def _to_F_parameters(C_scanner: np.ndarray, X: np.ndarray) -> np.ndarray:
    """A (6, 6) covariance of a scanner twist of ``T_F_from_scanner`` in F's parameters (deg, mm)."""
    A = -adjoint(X)  # the same motion as a delta in F: xi = -Ad(T_sf) delta, so delta = -Ad(T_fs) xi
    s = deg_mm_scale()
    C = A @ C_scanner @ A.T * np.outer(s, s)
    return 0.5 * (C + C.T)


def _f_tail(F: float, d1: int, d2: int) -> float:
    """P(F(d1, d2) > F): the regularised incomplete beta through :func:`~chic_register.fit.checks.gamma_p`'s
    relative, exact for the even ``d1`` and a normal approximation otherwise (Paulson)."""
    if not F > 0:
        return 1.0
    if d1 == 2:
        return (1.0 + 2.0 * F / d2) ** (-0.5 * d2)
    # Paulson's normal approximation of the F distribution (good to ~1e-3 here; the test's threshold is 1e-3)
    a, b = 2.0 / (9.0 * d1), 2.0 / (9.0 * d2)
    f = F ** (1.0 / 3.0)
    z = ((1 - b) * f - (1 - a)) / math.sqrt(b * f * f + a)
    return 0.5 * (1.0 - gamma_p(0.5, 0.5 * z * z)) if z > 0 else 1.0 - 0.5 * (1.0 - gamma_p(0.5, 0.5 * z * z))
