"""Statistics of a solved fit, from its own residuals: how precise it is and whether a stretch explains it.

Two of the verification's tests (:mod:`chic_register.verify.pixels`) ask the
fit itself rather than the image: :func:`pose_precision` (the predicted error
from the residual scatter, which a damaged image widens) and
:func:`stretch_test` (a wrong pixel spacing the pose absorbed leaves residuals
a stretch explains). Both are first order at the solution, over the tubes the
fit matched.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from chic_register.errors import ImprecisePose
from chic_register.fit.refine import scanner_crossing_jacobian
from chic_register.model.pose import invert
from chic_register.model.tube_model import exp_se3, plane_crossings, skew
from chic_register.util.roots import bracketed_root

#: The predicted error is held to the trust limits (:data:`~chic_register.options.TRE_TOL_MM`,
#: :data:`~chic_register.options.ROT_TOL_DEG`) at this many standard deviations of its own predicted error
#: (first-order covariance of the fit: residual scatter through the crossings' Jacobian). 3: a 0.3 % tail per
#: direction.
PRECISION_SIGMAS = 3.0
#: A pose refitted without a section the damage pulled off (chic_register.fit.accuracy.drop_section_outliers) is held to
#: this many: what moved one section may have moved others by less than their noise shows, along the direction a
#: single slice knows least. In the false-lock hunt a tool in the bore pulled one section of a near-normal slice off
#: and turned the rest's consistent pose 0.99 deg at 4.4 of its predicted sigmas (seed 0, case 1795).
OUTLIER_PRECISION_SIGMAS = 4.5
#: The residual scatter of 6-10 tubes is itself uncertain (12-14 degrees of freedom): the scatter used is its
#: upper bound at this confidence (chi-square), so a few lucky residuals do not make a pose look precise.
SCATTER_CONFIDENCE = 0.9
#: Floor of the per-coordinate position scatter (pixels): the residual bias of a centroid in a noise-free image.
POSITION_FLOOR_PX = 0.005
#: A stretch of the section positions along the image rows or columns is a wrong pixel spacing when it explains
#: the residuals at this tail probability (F test, 2 parameters) ...
STRETCH_P = 1e-3
#: ... and is at least this large: clinical scanners' gradient calibration is good to well under 1 %, and a 2 %
#: error moves a tube 25 mm off-centre by 0.5 mm ...
STRETCH_MIN = 0.02
#: ... or moves the pose by more than this share of the trust limits when fitted with it: a smaller stretch turns the
#: pose too, by about ``s cot(tilt)`` rad (the sections' ellipse read as a tilt); a 0.66 % one (a 77-pixel matrix
#: zoomed 2x by mapping its first and last pixels, declared at half the spacing) turned a 36 deg slice 0.53 deg.
#: The share is the trust limits' 1 sigma: such a move is a systematic error as large as the noise allowed.
STRETCH_MOVE_SHARE = 1.0 / PRECISION_SIGMAS


#: The first-order covariance of a pose holds only where the crossings' Jacobian barely changes over the pose's own
#: predicted error: it is evaluated again at poses this many of its standard deviations along its worst rotation and
#: its worst displacement, and the worst of them is the pose's (the region's ends: the Jacobian changes smoothly
#: between them, and each pose tried costs a verified slice about half a millisecond). Where the crossings fix a
#: direction only to second order (a single slice normal to the rods of N-localizer plates: a turn about the
#: left-right axis moves no crossing to first order), the Jacobian's hold on it there is the fit's own error along it,
#: which vanishes within that error: the precision is then that of the pose where it vanishes.
REGION_SIGMAS = (-3.0, 3.0)


def _crossings_jacobian(model, fit, Ss, T_F_from_scanner, exclude):
    """The matched tubes' crossings' Jacobian at a pose (rows: 2 per crossing, 6 columns), or None."""
    Js = []
    for j, S in enumerate(Ss):
        q, tan, _, _ = plane_crossings(model, T_F_from_scanner @ S, margin_mm=1e-9)
        use = fit.assignments[j] >= 0
        if exclude is not None:
            use &= ~np.isin(np.asarray(model.ids), list(exclude[j]))
        k = np.flatnonzero(use)
        if k.size:
            Js.append(scanner_crossing_jacobian(q[k], tan[k], S).reshape(-1, 6))
    return np.concatenate(Js) if Js else None


def _covariance(J, sigma: float):
    """``sigma^2 (J^T J)^-1`` (6, 6), or None when singular."""
    try:
        C = sigma * sigma * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    return C if np.all(np.isfinite(C)) else None


def pose_precision(model, fit, Ss, pixel_mm: float, exclude=None):
    """1-sigma bounds ``(TRE at the frame centre (mm), rotation (deg))`` of a fit, to first order: the largest
    eigenvalue of each block of the twist's covariance (:func:`_twist_terms`) is the worst direction, and the
    worst over the poses of :data:`REGION_SIGMAS` is the fit's."""
    terms = _twist_terms(model, fit, Ss, pixel_mm, exclude)
    C = None if terms is None else _covariance(*terms)
    if C is None:
        return math.inf, math.inf
    sigma = terms[1]
    lever = _frame_centre_scanner(model, fit)
    tre, rot = worst_errors(C, lever)
    for step in _worst_steps(C, lever):
        for t in REGION_SIGMAS:
            Jt = _crossings_jacobian(model, fit, Ss, fit.T_F_from_scanner @ exp_se3(t * step), exclude)
            Ct = None if Jt is None else _covariance(Jt, sigma)
            if Ct is None:
                return math.inf, math.inf
            tre_t, rot_t = worst_errors(Ct, lever)
            tre, rot = max(tre, tre_t), max(rot, rot_t)
    return tre, rot


def position_precision(model, fit, Ss, sigma_mm: float, exclude=None) -> tuple[float, float]:
    """1-sigma bounds ``(TRE at the frame centre (mm), rotation (deg))`` of a pose whose matched sections each lie
    ``sigma_mm`` (per coordinate) from where it puts them: the worst directions of ``sigma^2 (J^T J)^-1``, ``J`` the
    crossings' Jacobian (:func:`_crossings_jacobian`). ``(inf, inf)`` when not determined."""
    J = _crossings_jacobian(model, fit, Ss, fit.T_F_from_scanner, exclude)
    C = None if J is None else _covariance(J, sigma_mm)
    if C is None:
        return math.inf, math.inf
    return worst_errors(C, _frame_centre_scanner(model, fit))


def twist_covariance(model, fit, Ss, pixel_mm: float, exclude=None) -> np.ndarray | None:
    """The covariance (6, 6) of a fit's twist (scanner frame) at its pose, to first order (:func:`_twist_terms`);
    None when not determined."""
    terms = _twist_terms(model, fit, Ss, pixel_mm, exclude)
    return None if terms is None else _covariance(*terms)


def weakest_rotation(C: np.ndarray, fit) -> tuple[np.ndarray, float]:
    """The least determined rotation of a twist covariance ``C`` (6, 6; scanner frame): its axis in F (3,, unit)
    and its 1-sigma (deg)."""
    w, V = np.linalg.eigh(np.asarray(C, float)[:3, :3])
    axis = np.asarray(fit.T_F_from_scanner, float)[:3, :3] @ V[:, -1]
    axis = axis if axis[int(np.argmax(np.abs(axis)))] > 0 else -axis
    return axis, math.degrees(math.sqrt(max(float(w[-1]), 0.0)))


def weakest_rotation_text(C: np.ndarray, fit) -> str:
    """``C``'s least determined rotation in words: "the rotation about F's x axis ..." or about the axis's components."""
    axis, _ = weakest_rotation(C, fit)
    k = int(np.argmax(np.abs(axis)))
    where = (f"F's {'xyz'[k]} axis" if abs(axis[k]) >= 0.95
             else "the axis (" + ", ".join(f"{v:.2f}" for v in axis) + ") of F")
    return f"the rotation about {where} is the least determined"


def _twist_terms(model, fit, Ss, pixel_mm: float, exclude=None):
    """``(J, sigma)``: the matched crossings' Jacobian of a fit's twist (scanner frame) and the per-coordinate
    scatter; None when not determined.

    The crossings' Jacobian (:func:`chic_register.model.tube_model.crossing_jacobian`)
    of every matched tube, with a per-coordinate scatter from the residuals
    (``sum r^2`` over its :data:`SCATTER_CONFIDENCE` chi-square bound with
    ``2 n - 6`` degrees of freedom, at least :data:`POSITION_FLOOR_PX`), gives the
    covariance of the twist ``(omega, v)`` of ``T_F_from_scanner``; the frame
    centre ``(0, 0, L/2)`` then moves by ``[p]x omega - v``. ``exclude``: per
    slice, tube ids that are no evidence (merged sections).
    """
    n, sq = 0, 0.0
    for j in range(len(Ss)):
        use = fit.assignments[j] >= 0
        if exclude is not None:
            use &= ~np.isin(np.asarray(model.ids), list(exclude[j]))
        k = np.flatnonzero(use)
        r = fit.residuals[j][k]
        n += k.size
        sq += float(np.sum(r[np.isfinite(r)] ** 2))
    dof = 2 * n - 6
    J = _crossings_jacobian(model, fit, Ss, fit.T_F_from_scanner, exclude)
    if J is None or dof <= 0:
        return None
    chi2_low = 2.0 * gamma_p_inverse(0.5 * dof, 1.0 - SCATTER_CONFIDENCE)  # chi-square quantile, dof degrees
    sigma = max(math.sqrt(sq / chi2_low), POSITION_FLOOR_PX * pixel_mm)
    return J, sigma


def _worst_steps(C: np.ndarray, lever_mm: np.ndarray) -> list[np.ndarray]:
    """One standard deviation of the twist (6,) along the worst rotation and along the worst displacement of the
    point ``lever_mm``, each with the other parameters at their conditional means (the fit's own compensation)."""
    A = np.hstack([skew(np.asarray(lever_mm, float)), -np.eye(3)])
    steps = []
    for B in (np.hstack([np.eye(3), np.zeros((3, 3))]), A):
        M = B @ C @ B.T
        w, V = np.linalg.eigh(M)
        e = V[:, -1]
        if w[-1] <= 0:
            continue
        steps.append(C @ B.T @ e / math.sqrt(w[-1]))  # cov(x, e.y) / sd(e.y): x's conditional move per sd of e.y
    return steps


#: A covariance's (deg, mm) parameters as a twist's (rad, mm): multiply both sides by ``outer(TO_TWIST, TO_TWIST)``.
TO_TWIST = np.array([math.radians(1.0)] * 3 + [1.0] * 3)


def check_noise_precision(unc, model, opts, sigmas: float = PRECISION_SIGMAS, scale_prior: bool = False) -> None:
    """:class:`~chic_register.errors.ImprecisePose` unless the pose's covariance from the pixel noise (``unc``, a
    :class:`~chic_register.precision.uncertainty.PoseUncertainty`) keeps ``sigmas`` of its error within the trust limits.

    The verification's precision test (:func:`pose_precision`) reads the
    scatter of the fit's own residuals; with 6-9 sections a lucky small
    scatter makes a pose look more precise than its pixels allow (hunt seed
    2: a ghosted slice 0.61 deg off, and a thick slab 0.52 deg off, passed on
    residuals at a third of their noise). The pose must pass both.
    ``scale_prior``: the covariance holds an unmeasured scale (``SolveOptions.scale_sd``), and the message says so.
    """
    tre, rot = worst_errors(unc.covariance * np.outer(TO_TWIST, TO_TWIST), np.array([0.0, 0.0, 0.5 * model.length_mm]))
    if sigmas * tre > opts.trust_tre_mm or sigmas * rot > opts.trust_rot_deg:
        source = "the pixel noise and the image's unmeasured scale (--scale-sd)" if scale_prior else "the pixel noise"
        advice = ("several slices or a volume measure the scale, and a geometry file calibrated on this scanner "
                  "(chic-register calibrate) knows it better" if scale_prior else
                  "a tilted slice or several parallel slices are more precise")
        raise ImprecisePose(f"the pose is not precise enough to trust: {sigmas:g} sigma of its error predicted from "
                            f"{source} is {sigmas * tre:.2f} mm at the frame centre and {sigmas * rot:.2f} deg "
                            f"(limits {opts.trust_tre_mm:g} mm, {opts.trust_rot_deg:g} deg; {advice}; --trust MM DEG "
                            f"sets the limits)",
                            {"sigma_tre_mm": round(tre, 4), "sigma_rot_deg": round(rot, 4)})


def _frame_centre_scanner(model, fit) -> np.ndarray:
    """(3,) the frame centre (0, 0, L/2) of F in the scanner frame at the fit's pose (mm)."""
    T_sf = invert(fit.T_F_from_scanner)
    return T_sf[:3, :3] @ np.array([0.0, 0.0, 0.5 * model.length_mm]) + T_sf[:3, 3]


def worst_errors(C: np.ndarray, lever_mm: np.ndarray) -> tuple[float, float]:
    """1-sigma ``(displacement (mm), rotation (deg))`` in the worst direction, from the covariance ``C`` (6, 6) of a
    twist ``(omega (rad), v (mm))``: a point at ``lever_mm`` (3,) from the turns' centre moves by ``omega x lever + v``
    (either sign convention of the twist gives the same covariance of it)."""
    A = np.hstack([skew(np.asarray(lever_mm, float)), -np.eye(3)])
    tre = math.sqrt(max(float(np.linalg.eigvalsh(A @ C @ A.T).max()), 0.0))
    rot = math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(C[:3, :3]).max()), 0.0)))
    return tre, rot


def gamma_p(a: float, x: float) -> float:
    """The regularised lower incomplete gamma function P(a, x) (``scipy.special.gammainc``), a > 0.

    Series below ``x = a + 1``, Lentz's continued fraction for ``1 - P``
    above (Numerical Recipes' ``gammp``); to ~1e-14. Here rather than
    ``scipy.special``, whose import costs a fifth of a one-shot solve.
    """
    if x <= 0.0:
        return 0.0
    log_front = -x + a * math.log(x) - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        n = 0
        while abs(term) > abs(total) * 1e-16 and n < 10000:
            n += 1
            term *= x / (a + n)
            total += term
        return min(1.0, total * math.exp(log_front))
    tiny = 1e-300
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    h = d
    for i in range(1, 10000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        h *= d * c
        if abs(d * c - 1.0) < 1e-16:
            break
    return max(0.0, 1.0 - math.exp(log_front) * h)


@functools.lru_cache(maxsize=256)
def gamma_p_inverse(a: float, p: float) -> float:
    """The x with ``gamma_p(a, x) = p`` (``scipy.special.gammaincinv``), for 0 < p < 1 (memoised: the pose checks
    ask for the same few degrees of freedom on every pose)."""
    hi = a + 10.0 * math.sqrt(a) + 10.0
    while gamma_p(a, hi) < p:
        hi *= 2.0
    return bracketed_root(lambda x: gamma_p(a, x) - p, 0.0, hi, -p, gamma_p(a, hi) - p, xtol=1e-12 * hi)


def _stretch_terms(model, fit, xys, Ss):
    """The pose Jacobian ``Jp`` (m, 6), the stretch Jacobian ``Js`` (m, 2) and the residuals ``r`` (m,) of
    :func:`stretch_test` (whitened as the fit weighed them), or None without residuals."""
    meas = getattr(fit, "measurements", None)
    Jp, Js, rs = [], [], []
    for j, S in enumerate(Ss):
        q, tan, _, inside = plane_crossings(model, fit.T_F_from_scanner @ S, margin_mm=1e-9)
        a = fit.assignments[j]
        k = np.flatnonzero((a >= 0) & inside)
        if k.size == 0:
            continue
        xy = np.asarray(meas[j][0] if meas is not None else xys[j], float)[a[k]]
        L = meas[j][1][k] if meas is not None else np.broadcast_to(np.eye(2), (k.size, 2, 2))
        J = scanner_crossing_jacobian(q[k], tan[k], S)
        D = np.zeros((k.size, 2, 2))
        D[:, 0, 0], D[:, 1, 1] = -xy[:, 0], -xy[:, 1]  # d(q - (1 + s) xy) / ds
        Jp.append(np.einsum("kij,kjl->kil", L, J).reshape(-1, 6))
        Js.append(np.einsum("kij,kjl->kil", L, D).reshape(-1, 2))
        rs.append(np.einsum("kij,kj->ki", L, q[k] - xy).ravel())
    if not rs:
        return None
    return np.concatenate(Jp), np.concatenate(Js), np.concatenate(rs)


def anisotropic_stretch(model, fit, xys, Ss) -> tuple[float, float]:
    """The difference of the column and row stretches the tube positions fit with the pose, and its standard error
    (from the residuals' scatter); ``(nan, inf)`` when the positions cannot tell (too few, or degenerate)."""
    terms = _stretch_terms(model, fit, xys, Ss)
    if terms is None:
        return math.nan, math.inf
    Jp, Js, r = terms
    dof = r.size - 8
    if dof <= 0:
        return math.nan, math.inf
    Q, _ = np.linalg.qr(Jp)
    Js_perp = Js - Q @ (Q.T @ Js)
    r_perp = r - Q @ (Q.T @ r)
    s, *_ = np.linalg.lstsq(Js_perp, -r_perp, rcond=None)
    rest = max(float(r_perp @ r_perp) - float(np.sum((Js_perp @ s) ** 2)), 0.0)
    try:
        cov = (rest / dof) * np.linalg.inv(Js_perp.T @ Js_perp)
    except np.linalg.LinAlgError:
        return math.nan, math.inf
    c = np.array([1.0, -1.0])
    var = float(c @ cov @ c)
    return float(s[0] - s[1]), (math.sqrt(var) if var >= 0 and math.isfinite(var) else math.inf)


def stretch_test(model, fit, xys, Ss):
    """Does a stretch of the image along its rows or columns explain the fit's residuals? ``(scale, F, p)``.

    A wrong pixel spacing scales every position about the image origin
    (``xy = rc * spacing``); a tilt of the pose absorbs part of it, the
    rest stays in the residuals as a pattern no noise makes. The fit is
    extended, to first order at its solution, by the two scales
    (``xy -> (1 + s) * xy``); ``F`` is the share of the residual energy the
    two extra parameters explain, over what is left, per degree of freedom
    (an F(2, m - 8) statistic, ``m`` the residual count) and ``p`` its tail
    probability (closed form for 2 numerator degrees of freedom). ``scale``
    (2,): the fitted relative stretch along x (columns) and y (rows);
    ``moved``: ``(mm at the frame centre, deg)`` the pose moves by when the
    stretch is fitted with it (the error a stretch of the image this size
    puts in the pose; ``(0, 0)``, not computed, when ``p`` is not below
    :data:`STRETCH_P`). Returns ``(scale, F, p, moved)``. The
    residuals are whitened as the fit weighed them (``fit.measurements``).
    """
    terms = _stretch_terms(model, fit, xys, Ss)
    if terms is None:
        return np.zeros(2), 0.0, 1.0, (0.0, 0.0)
    Jp, Js, r = terms
    dof = r.size - 8
    if dof <= 0:
        return np.zeros(2), 0.0, 1.0, (0.0, 0.0)
    Q, _ = np.linalg.qr(Jp)
    Js_perp = Js - Q @ (Q.T @ Js)
    r_perp = r - Q @ (Q.T @ r)
    s, *_ = np.linalg.lstsq(Js_perp, -r_perp, rcond=None)
    explained = float(np.sum((Js_perp @ s) ** 2))
    rest = max(float(r_perp @ r_perp) - explained, 1e-30)
    F = (explained / 2.0) / (rest / dof)
    p = (1.0 + 2.0 * F / dof) ** (-0.5 * dof)
    if p >= STRETCH_P:  # not significant: the move is not asked for (the common path)
        return s, F, p, (0.0, 0.0)
    twist = np.linalg.lstsq(Jp, Js @ s, rcond=None)[0]  # the pose's move when the stretch is fitted with it
    return s, F, p, worst_errors(np.outer(twist, twist), _frame_centre_scanner(model, fit))
