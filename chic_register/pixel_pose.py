"""The pose refitted on the pixels themselves: Gauss-Newton on the six pose parameters through the section model.

An option (``SolveOptions.pixel_pose_steps``, off by default: it did not
measurably help, see below). The section fit (:mod:`chic_register.section`)
reduces each tube's window to a position and its 2 x 2 information, then
fits the pose to those positions; what the pixels say about the pose
through the SHAPE of each section (its length and direction follow the
tube's tilt to the plane) is dropped. Here every window pixel's model
(:func:`~chic_register.section.section_model` drawn at the pose's
crossings, ``S``) is fitted to the pixels directly, over the six pose
parameters at once: the pose's Jacobian by forward differences of the
model (vectorised across tubes, one model evaluation per pose parameter).

The data are magnitudes: where the signal is a few noise SDs or less (the
section's edges, which carry the shape) their mean is not linear in the
signal, and a fit of ``y = b + a S`` reads that as a wider section, i.e.
as a tilt (measured: the normal-angle error at a 30 deg slice 1.32x the
bound instead of 0.90x). So the squared magnitudes are fitted: for a
signal ``b + g S`` plus complex Gaussian (or any additive zero-mean) noise,
``E[y^2] = c0 + c1 S + c2 S^2`` exactly, with per-tube ``c`` (linear,
eliminated), weighted by ``1 / var(y^2) = 1 / (4 sigma^2 (A^2 + sigma^2))``.
The pose is perturbed about a point of the first slice near its sections
(the mean crossing), so that a turn does not also shift the sections by a
long lever (the CRLB's derivatives turn about the slice centre for the same
reason: :func:`chic_register.crlb.image_jacobian`).

Safeguards (:func:`pixel_pose_refine`): a step is kept only if the weighted
sum of squared residuals at the new pose (coefficients refitted) is lower,
and only if its length in the step's own predicted standard deviations
(``sqrt(dxi' I dxi)``, ``I`` the Gauss-Newton information) is at most
``max_step_sigma``: the section fit's pose is already within about one
standard deviation of the truth, so a longer step means the model does not
describe these pixels, and the section fit's pose stands.

Measured (``benchmarks/bench_accuracy.py --crlb --mode pixel`` against
``--mode default``, 100 draws, 38 poses, Rician SNR 10, 20, 50; README,
accuracy section): one step changes each pose's RMS error / CRLB by a
median of -1 to +2 % (extremes -18 % and +13 %), leaves the worst poses as
they are, and costs about 5.5 ms CPU per slice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .pose import invert
from .section import Windows, section_model
from .tube_model import TubeModel, _exp_se3, plane_crossings

#: Forward-difference steps of the pose: rad for the turns, mm for the shifts (~1e-3 of a pixel at 15 mm).
STEP_RAD = 1e-4
STEP_MM = 1e-3
#: The weights' noise floor, as a share of the fluid signal (SNR 100).
MIN_NOISE = 0.01


@dataclass(frozen=True, eq=False)
class PixelPose:
    """The outcome: ``T_F_from_scanner`` (4x4), whether a step was kept (``moved``), the steps' lengths in their
    predicted standard deviations (``step_sigma``, one per step tried), the sum of squared residuals before and
    after (pixel units), and the pose's 6x6 information (``info``, (rad, mm) about ``centre_I``) at the last pose."""

    T_F_from_scanner: np.ndarray
    moved: bool
    step_sigma: tuple
    ssr_before: float
    ssr_after: float
    info: np.ndarray


def _model_at(model: TubeModel, X: np.ndarray, Ss, wins, slices, thickness_samples: int):
    """The section model of every window pixel of every slice at ``T_F_from_scanner = X``, concatenated (P,)."""
    out = []
    for S, win, sl in zip(Ss, wins, slices):
        T = X @ S
        q, tan, _, _ = plane_crossings(model, T, margin_mm=1e-9)
        out.append(section_model(model, T, q, tan, win, sl.pixel_spacing_mm, float(sl.slice_thickness_mm),
                                 thickness_samples)[0])
    return np.concatenate(out)


def _group_fit(R: np.ndarray, Y: np.ndarray, w: np.ndarray, group: np.ndarray, G: int):
    """Per group weighted least squares of each column of ``Y`` (P, n) on the regressors ``R`` (P, m).

    Returns ``(residuals (P, n), coefficients (G, m, n))``; a group whose
    normal matrix is singular keeps its columns as residuals.
    """
    m, n = R.shape[1], Y.shape[1]
    Rw = R * w[:, None]
    N = np.zeros((G, m, m))
    B = np.zeros((G, m, n))
    for i in range(m):
        for k in range(i, m):
            N[:, i, k] = N[:, k, i] = np.bincount(group, Rw[:, i] * R[:, k], G)
        for c in range(n):
            B[:, i, c] = np.bincount(group, Rw[:, i] * Y[:, c], G)
    coef = np.zeros((G, m, n))
    ok = np.linalg.cond(N) < 1e12
    if ok.any():
        coef[ok] = np.linalg.solve(N[ok], B[ok])
    return Y - np.einsum("pm,pmn->pn", R, coef[group]), coef


def _weighted_fit(S: np.ndarray, y2: np.ndarray, w0: np.ndarray, sig2: float, group: np.ndarray, G: int):
    """Per tube fit of the squared magnitudes ``y2`` (P, 1) on :func:`_regressors` of ``S`` with weights
    ``1 / var(y^2) = 1 / (4 sigma^2 (A^2 + sigma^2))`` (``A^2 + sigma^2`` = the fitted mean less ``sigma^2``;
    the mean from a first fit weighted ``w0``). Returns ``(residuals (P, 1), coefficients (G, 3, 1), weights)``."""
    R = _regressors(S)
    res = _group_fit(R, y2, w0, group, G)[0]
    w = 1.0 / (4.0 * sig2 * np.maximum(y2[:, 0] - res[:, 0] - sig2, sig2))
    res, coef = _group_fit(R, y2, w, group, G)
    return res, coef, w


def _regressors(S: np.ndarray) -> np.ndarray:
    """Per pixel ``[1, S, S^2]``: the squared magnitude of ``b + g S`` plus noise has mean ``c0 + c1 S + c2 S^2``."""
    return np.column_stack([np.ones_like(S), S, S * S])


def pixel_pose_refine(model: TubeModel, T_F_from_scanner: np.ndarray, Ss, slices, windows, assignments, *,
                      steps: int = 1, max_step_sigma: float = 3.0, noise_sigma: float = 1.0,
                      thickness_samples: int = 5) -> PixelPose:
    """Up to ``steps`` Gauss-Newton steps of the pose on the pixels of ``windows`` (see the module docstring).

    ``Ss``: each slice's ``T_scanner_from_image``; ``windows``: per slice the
    :class:`~chic_register.section.Windows` of the section fit; ``assignments``:
    per slice (K,) blob index or -1 (only assigned tubes' pixels are used);
    ``noise_sigma``: the pixel noise, scaling the information (the step test is
    in its units). Returns :class:`PixelPose`; with no usable window the pose
    comes back unchanged.
    """
    X = np.asarray(T_F_from_scanner, dtype=float).copy()
    K = len(model.ids)
    wins, ys, groups, used = [], [], [], []
    for j, (sl, win, a) in enumerate(zip(slices, windows, assignments)):
        if win is None:
            continue
        keep = a[win.owner] >= 0
        w = Windows(win.rows[keep], win.cols[keep], win.owner[keep])
        if w.owner.size == 0:
            continue
        wins.append(w)
        ys.append(np.asarray(sl.pixels, dtype=float)[w.rows, w.cols])
        groups.append(w.owner + j * K)
        used.append(j)
    if not wins:
        return PixelPose(X, False, (), float("nan"), float("nan"), np.zeros((6, 6)))
    Ss_u, sl_u = [Ss[j] for j in used], [slices[j] for j in used]
    y = np.concatenate(ys)
    _, group = np.unique(np.concatenate(groups), return_inverse=True)
    G = int(group.max()) + 1
    # the perturbation: T_F_from_scanner(xi) = X @ P exp(xi) P^-1, P the first slice's frame moved to its mean crossing
    S0 = Ss_u[0]
    q0 = plane_crossings(model, X @ S0, margin_mm=1e-9)[0]
    own0 = np.unique(wins[0].owner)
    P = S0.copy()
    P[:3, 3] = S0[:3, :3] @ np.r_[q0[own0].mean(axis=0), 0.0] + S0[:3, 3]
    P_inv = invert(P)
    h = np.array([STEP_RAD] * 3 + [STEP_MM] * 3)
    y2 = (y * y)[:, None]
    m0 = _model_at(model, X, Ss_u, wins, sl_u, thickness_samples)
    # the weights' noise: at least MIN_NOISE of the fluid signal (a clean or synthetic image reads as noise ~0,
    # which would weight the background pixels without bound)
    coef1 = _group_fit(_regressors(m0), y2, np.ones_like(m0), group, G)[1][:, :, 0]
    fluid = float(np.median(np.sqrt(np.maximum(coef1.sum(axis=1), 0.0))))
    sig2 = max(noise_sigma, MIN_NOISE * fluid, 1e-12) ** 2
    res, coef, w = _weighted_fit(m0, y2, np.ones_like(m0), sig2, group, G)
    ssr0 = ssr = float(res[:, 0] ** 2 @ w)
    tried, moved = [], False
    info = np.zeros((6, 6))
    for _ in range(max(0, int(steps))):
        J = np.empty((y.size, 6))
        for i in range(6):
            e = np.zeros(6)
            e[i] = h[i]
            J[:, i] = (_model_at(model, X @ P @ _exp_se3(e) @ P_inv, Ss_u, wins, sl_u, thickness_samples) - m0) / h[i]
        # d E[y^2] / d xi = (c1 + 2 c2 S) dS/dxi; the per-tube coefficients eliminated with their regressors
        slope = coef[group, 1, 0] + 2.0 * coef[group, 2, 0] * m0
        A_res = _group_fit(_regressors(m0), slope[:, None] * J, w, group, G)[0]
        Aw = A_res * w[:, None]
        H = A_res.T @ Aw
        try:
            xi = np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(6), Aw.T @ res[:, 0])
        except np.linalg.LinAlgError:
            break
        info = H
        length = float(np.sqrt(max(xi @ info @ xi, 0.0)))
        tried.append(length)
        if not (np.isfinite(length) and length <= max_step_sigma):
            break
        X_new = X @ P @ _exp_se3(xi) @ P_inv
        m_new = _model_at(model, X_new, Ss_u, wins, sl_u, thickness_samples)
        res_new = _group_fit(_regressors(m_new), y2, w, group, G)[0]
        ssr_new = float(res_new[:, 0] ** 2 @ w)
        if not ssr_new < ssr:
            break
        # kept: the weights follow the model at the new pose (compared at the old weights, so the test is fair)
        X, m0, moved = X_new, m_new, True
        res, coef, w = _weighted_fit(m0, y2, w, sig2, group, G)
        ssr = float(res[:, 0] ** 2 @ w)
    return PixelPose(X, moved, tuple(tried), ssr0, ssr, info)
