"""Blobs wider than the channels: the pose fitted to the pixels through a blurred model of all sections at once.

Real images often show the fluid wider than the channel drawn (point spread,
partial volume, fluid spreading in a printed channel). Then neighbouring
sections (a helix running beside its straight tube) merge, a blob's centroid
is pulled toward its neighbour, and a pose fitted to centroids is off by a
few tenths of a millimetre with residuals well above the noise: the
precision test rightly refuses it.

Here the expected image is modelled instead: every section's analytic model
(:func:`chic_register.fit.section.section_model`) drawn on a box around it,
blurred by a Gaussian point spread (:func:`chic_register.imaging.psf.gaussian_blur`),
and the sections summed, so that merged neighbours are two terms of one
model. The pixels of the boxes are fitted by ``b + sum_k a_k M_k(pose)``
(one fluid level per tube, an offset) with Gauss-Newton over the six pose
parameters (the model's pose derivatives by forward differences; the
levels and offset solved jointly each step), after choosing the blur that
explains the pixels best, and a stretch of the image along its rows and
columns (a wrong pixel spacing would otherwise be absorbed by a tilt: the
solver refuses a significant one beyond 2 %). The pose's covariance follows from the same
normal equations with the noise from the residuals, over thousands of
pixels (the sandwich estimate, each pixel's squared residual its variance),
so a model that does not fit widens it; a smaller stretch the pixels show
(a scanner's 0.5 % along one axis) is not fitted, and how far it pulls the
pose is added to the covariance.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from chic_register.detect.blobs import median
from chic_register.detect.detected import DetectedSlice
from chic_register.errors import NoLock
from chic_register.fit.checks import STRETCH_MIN, worst_errors
from chic_register.fit.refine import refine
from chic_register.fit.section import section_model
from chic_register.fit.windows import Windows
from chic_register.imaging.psf import gaussian_blur
from chic_register.model.pose import invert
from chic_register.model.pose_params import deg_mm_scale
from chic_register.model.tube_model import (
    TubeModel,
    exp_se3,
    plane_crossings,
    poses_distinct,
    section_box,
    section_extent,
)

#: Point-spread sigmas tried (in tube radii; 0.35 r widens a 6 px blob to ~1.4x, 1.0 r to ~2.5x).
SIGMAS_RADII = (0.2, 0.35, 0.5, 0.7, 1.0, 1.4)
#: Each box reaches this many point-spread sigmas (plus a pixel) beyond the sharp section.
REACH_SIGMAS = 3.0
#: Gauss-Newton iterations at most, and the step (deg, mm) below which it has converged.
ITERATIONS = 8
DONE_DEG, DONE_MM = 1e-3, 1e-3
#: Forward-difference steps: rad for the turns, mm for the shifts, pixels for the blur, the stretch's share.
STEP_RAD, STEP_MM, STEP_PX, STEP_STRETCH = 2e-4, 2e-3, 1e-2, 1e-3
#: The image's stretch is fitted within +-this share (a wrong pixel spacing; the verification refuses above 2 %).
MAX_STRETCH = 0.3
#: A fitted stretch this many of its standard deviations from zero (and above fit_checks.STRETCH_MIN) is refused.
STRETCH_SIGMAS = 3.0
#: The (x, y) stretch is shown by the pixels when its chi-square (2 degrees of freedom, under its covariance) passes
#: the two-sided tail of STRETCH_SIGMAS (2.7e-3): the chi-square's tail with 2 dof is exp(-x / 2). Both axes count
#: together: a real slice 0.4 % long along x and 0.5 % short along y (2.5 and 2.8 sigma) pulls its pose 1 deg.
STRETCH_SHOWN_CHI2 = -2.0 * math.log(math.erfc(STRETCH_SIGMAS / math.sqrt(2.0)))
#: The pixel fit uses at most this many slices, spread over a longer series (its cost grows with them: a wide
#: 26-slice Z-frame volume took 4.5 s CPU instead of 0.75 s). Dozens of slices do not make the blob pose precise:
#: merged neighbours pull the centres the same way in every slice (a 1.3x needle-guide volume: 0.29 mm off at a
#: predicted 0.04 mm from 18 slices' centres).
BLURRED_MAX_SLICES = 4
#: Sub-planes across the slab for the sharp model (the blur hides finer detail).
THICKNESS_SAMPLES = 3


@dataclass(frozen=True, eq=False)
class BlurredFit:
    """The outcome: ``T_F_from_scanner`` (4x4), the point spread (``psf_px``, sigma in pixels of the first slice),
    the pose's 6x6 covariance (``covariance``, twist (rad, mm) about ``centre_scanner`` in the scanner frame; from
    the fit with the pixel spacing as given, plus the pull of a stretch the pixels show, :data:`STRETCH_SHOWN_CHI2`),
    the image's ``stretch`` fitted with the pose in the first pass (x = columns, y = rows: the share by which the
    pixel spacing looks too small) and its standard deviation, the residual noise sigma and the pixel count."""

    T_F_from_scanner: np.ndarray
    psf_px: float
    covariance: np.ndarray
    centre_scanner: np.ndarray
    noise_sigma: float
    n_pixels: int
    stretch: tuple = (0.0, 0.0)
    stretch_sd: tuple = (0.0, 0.0)

    def covariance_F(self) -> np.ndarray:
        """The covariance in :data:`chic_register.precision.crlb.PARAMETER_ORDER` (deg, mm; rotation about F's axes through
        its origin, then translation, a point p of F moving by r x p + t): the fit's twist about ``centre_scanner``
        mapped to F's by central differences of :func:`_perturb`."""
        M = np.empty((6, 6))
        for i in range(6):
            h = np.zeros(6)
            h[i] = STEP_RAD if i < 3 else STEP_MM
            d = []
            for sign in (1.0, -1.0):
                # T_scanner_from_F after the twist is T_sf @ D, D the same motion in F
                D = self.T_F_from_scanner @ invert(_perturb(self.T_F_from_scanner, sign * h, self.centre_scanner))
                r = 0.5 * np.array([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
                d.append(np.concatenate([r, D[:3, 3]]))
            M[:, i] = (d[0] - d[1]) / (2.0 * h[i])
        s = deg_mm_scale()
        C = (M @ self.covariance @ M.T) * np.outer(s, s)
        return 0.5 * (C + C.T)

    def precision(self, length_mm: float) -> tuple[float, float]:
        """1-sigma bounds ``(TRE at the frame centre (0, 0, L/2) in mm, rotation in deg)``: the worst direction."""
        T_sf = invert(self.T_F_from_scanner)
        centre = T_sf[:3, :3] @ np.array([0.0, 0.0, 0.5 * length_mm]) + T_sf[:3, 3]
        return worst_errors(self.covariance, centre - self.centre_scanner)


@dataclass(frozen=True)
class _Box:
    """One tube's box in one slice: pixel rows r0:r1, columns c0:c1."""

    slice_index: int
    tube: int
    r0: int
    r1: int
    c0: int
    c1: int


def _boxes(model: TubeModel, T_F_from_I: np.ndarray, shape, spacing, thickness_mm: float, reach_px: float,
           j: int) -> list[_Box]:
    """A box around every tube section the pose puts in the image (clipped to it)."""
    rs, cs = spacing
    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=1e-9)
    half_len, half_wid, u = section_extent(model, tan, thickness_mm)
    ex, ey = section_box(half_len, half_wid, u)
    ex, ey = ex + reach_px * cs, ey + reach_px * rs
    H, W = shape
    out = []
    for k in np.flatnonzero(found):
        r0, r1 = max(int(math.floor((q[k, 1] - ey[k]) / rs)), 0), min(int(math.ceil((q[k, 1] + ey[k]) / rs)) + 1, H)
        c0, c1 = max(int(math.floor((q[k, 0] - ex[k]) / cs)), 0), min(int(math.ceil((q[k, 0] + ex[k]) / cs)) + 1, W)
        if r1 - r0 >= 3 and c1 - c0 >= 3 and (r1 - r0) * (c1 - c0) <= H * W // 4:
            out.append(_Box(j, int(k), r0, r1, c0, c1))
    return out


class _Problem:
    """The pixels of a set of boxes in one or more slices and the blurred model's columns at a pose."""

    def __init__(self, model, slices, Ss, boxes, sigma_px: float, blob_sets, assignments):
        self.model, self.slices, self.Ss, self.boxes, self.sigma_px = model, slices, Ss, boxes, sigma_px
        self.stretch = np.zeros(2)  # (x, y): the pixel spacing along columns and rows scaled by 1 + stretch
        self.tubes = sorted({b.tube for b in boxes})
        col = {k: i for i, k in enumerate(self.tubes)}
        # the fitted pixels: the union of the boxes, per slice (flat indices, sorted); per slice the boxes' pixels
        # (rows, cols, owner) for the sharp model and, per box, where its pixels sit in the fitted vector
        pix, self.per_slice, self.starts = [], [], []
        offset = 0
        for j, sl in enumerate(slices):
            mine = [b for b in boxes if b.slice_index == j]
            width = np.shape(sl.pixels)[1]
            flat = [(np.mgrid[b.r0:b.r1, b.c0:b.c1][0] * width + np.mgrid[b.r0:b.r1, b.c0:b.c1][1]).ravel()
                    for b in mine]
            union = np.unique(np.concatenate(flat)) if flat else np.zeros(0, int)
            pix.append(union)
            self.starts.append(offset)
            if mine:
                allflat = np.concatenate(flat)
                win = Windows(allflat // width, allflat % width, np.concatenate([np.full(f.size, b.tube)
                                                                                 for b, f in zip(mine, flat)]), False)
                where = [offset + np.searchsorted(union, f) for f in flat]
                self.per_slice.append((j, mine, win, where, [col[b.tube] for b in mine]))
            offset += union.size
        self.y = np.concatenate([np.asarray(sl.pixels, float).ravel()[p] for sl, p in zip(slices, pix)])
        # pixels of blobs no tube was matched to (a stray, another object) are not the model's: left out
        self.keep = np.ones(self.y.size, bool)
        for j, (b, a) in enumerate(zip(blob_sets, assignments)):
            used = {int(i) for i in a if i >= 0}
            if pix[j].size == 0:  # no section's box in this slice: nothing to leave out
                continue
            width = np.shape(slices[j].pixels)[1]
            for i, (r0, c0, mask) in enumerate(b.footprints):
                if i in used:
                    continue
                rr, cc = np.nonzero(mask)
                flat = (rr + r0) * width + (cc + c0)
                at = np.searchsorted(pix[j], flat)
                hit = (at < pix[j].size) & (pix[j][np.minimum(at, pix[j].size - 1)] == flat)
                self.keep[self.starts[j] + at[hit]] = False
        self.y = self.y[self.keep]
        self.offsets = np.ones((self.y.size, 1))  # one background level (a level per box competes with the tails)

    def columns(self, X: np.ndarray) -> np.ndarray:
        """(P, n_tubes) blurred section model of each tube at ``T_F_from_scanner = X`` on the fitted pixels."""
        M = np.zeros((self.keep.size, len(self.tubes)))
        for j, mine, win, where, cols in self.per_slice:
            sl = self.slices[j]
            T = X @ self.Ss[j]
            q, tan, _, _ = plane_crossings(self.model, T, margin_mm=1e-9)
            rs, cs = (float(v) for v in sl.pixel_spacing_mm)
            spacing = (rs * (1.0 + self.stretch[1]), cs * (1.0 + self.stretch[0]))
            sharp = section_model(self.model, T, q, tan, win, spacing, float(sl.slice_thickness_mm),
                                  THICKNESS_SAMPLES)[0]
            start = 0
            for b, idx, c in zip(mine, where, cols):
                n = idx.size
                img = gaussian_blur(sharp[start:start + n].reshape(b.r1 - b.r0, b.c1 - b.c0), self.sigma_px)
                start += n
                np.add.at(M[:, c], idx, img.ravel())
        return M[self.keep]

    def linear(self, M: np.ndarray):
        """Levels and offset ``(a (n_tubes,), residual (P,))`` of ``y = b + M a`` by least squares."""
        A = np.column_stack([M, self.offsets])
        coef = np.linalg.lstsq(A, self.y, rcond=None)[0]
        return coef[:M.shape[1]], self.y - A @ coef


def _perturb(X: np.ndarray, xi: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``T_F_from_scanner`` after the scanner-frame twist ``xi`` (rad, mm) about ``centre`` moves the fiducial."""
    C = np.eye(4)
    C[:3, 3] = centre
    Ci = np.eye(4)
    Ci[:3, 3] = -centre
    return X @ C @ invert(exp_se3(xi)) @ Ci


def _jacobian(prob: _Problem, X: np.ndarray, coef: np.ndarray, centre: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(P, 9) derivative of the model ``M a`` (levels ``coef`` held) along the six twists, the blur sigma and the
    image's stretch along x and y."""
    steps = np.array([STEP_RAD] * 3 + [STEP_MM] * 3)
    J = np.empty((prob.y.size, 9))
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = steps[i]
        J[:, i] = (prob.columns(_perturb(X, xi, centre)) @ coef - base) / steps[i]
    sigma = prob.sigma_px
    prob.sigma_px = sigma + STEP_PX
    J[:, 6] = (prob.columns(X) @ coef - base) / STEP_PX
    prob.sigma_px = sigma
    for i in range(2):
        prob.stretch[i] += STEP_STRETCH
        J[:, 7 + i] = (prob.columns(X) @ coef - base) / STEP_STRETCH
        prob.stretch[i] -= STEP_STRETCH
    return J


def blurred_fit(model: TubeModel, T_F_from_scanner: np.ndarray, slices, Ss, blob_sets, assignments,
                psf_px: float | None = None):
    """Fit the pose and the point spread to the pixels of ``slices`` (scanner frames ``Ss``) through the blurred
    section model.

    Starts at ``T_F_from_scanner`` (a pose within a fraction of a tube's
    width; ``assignments``: per slice (K,) its blob per tube, -1 for none:
    the footprints (``blob_sets``) of unmatched blobs are left out) and ``psf_px`` (the point spread's sigma in pixels, else the best
    of :data:`SIGMAS_RADII` at the start). Returns a :class:`BlurredFit`, or
    None when fewer than six sections are in the images.
    """
    px = float(max(slices[0].pixel_spacing_mm))
    r_px = 0.5 * median(model.diameter_mm) / px
    sigmas = [psf_px] if psf_px is not None else [f * r_px for f in SIGMAS_RADII]
    X = np.array(T_F_from_scanner, float)

    def problem(sigma):  # boxes reaching far enough for the blur to grow by half while fitted
        boxes = []
        for j, (sl, S) in enumerate(zip(slices, Ss)):
            boxes += _boxes(model, X @ S, np.shape(sl.pixels), tuple(float(v) for v in sl.pixel_spacing_mm),
                            float(sl.slice_thickness_mm), REACH_SIGMAS * 1.5 * sigma + 1.0, j)
        return _Problem(model, slices, Ss, boxes, sigma, blob_sets, assignments)

    best = None
    for sigma in sigmas:  # the blur that explains the pixels best at the start pose (per pixel: boxes differ)
        prob = problem(sigma)
        if len(prob.tubes) < 6:
            return None
        _, r = prob.linear(prob.columns(X))
        score = float(r @ r) / r.size
        if best is None or score < best[0]:
            best = (score, sigma, prob)
    _, sigma, prob = best
    # the turns are about the first slice's mean section (in scanner mm): a turn then barely shifts the sections
    q0 = plane_crossings(model, X @ Ss[0], margin_mm=1e-9)[0][prob.tubes]
    centre = (Ss[0] @ np.array([*q0.mean(axis=0), 0.0, 1.0]))[:3]
    # first with the image's stretch free (the test of the pixel spacing), then with the spacing as given: the pose
    # and its covariance (a stretch below the refusal threshold is the scanner's calibration: it is not fitted, but
    # where the pixels show it, how far it pulls the pose widens the covariance)
    X, stretch_fit = _gauss_newton(prob, X, centre, sigma, n_free=9)
    if stretch_fit is None:
        return None
    stretch, stretch_sd = prob.stretch.copy(), stretch_fit[1]
    prob.stretch = np.zeros(2)
    X, fitted = _gauss_newton(prob, X, centre, sigma, n_free=7)
    if fitted is None:
        return None
    cov, _, noise = fitted
    pose_cov = cov[:6, :6]
    C = stretch_fit[0]
    shown = np.linalg.inv(C[7:9, 7:9])
    if float(stretch @ shown @ stretch) > STRETCH_SHOWN_CHI2:
        # a stretch the pixels show, left out of the pose: its pull on the pose (the pose's regression on the
        # stretch in the free fit, times the stretch) is part of the pose's error, not a calibration to ignore
        pull = C[:6, 7:9] @ shown @ stretch
        pose_cov = pose_cov + np.outer(pull, pull)
    return BlurredFit(X, float(prob.sigma_px), pose_cov, centre, noise, int(prob.y.size),
                      tuple(float(v) for v in stretch), tuple(float(v) for v in stretch_sd))


def _gauss_newton(prob: _Problem, X: np.ndarray, centre: np.ndarray, sigma0: float, n_free: int):
    """Gauss-Newton of the pose, the blur (within half of ``sigma0`` either way) and, with ``n_free`` 9, the
    stretch: ``(X, (covariance (n_free, n_free), stretch sd (2,), noise sigma))``, the second None if singular."""
    M = prob.columns(X)
    coef, r = prob.linear(M)
    ssr = float(r @ r)
    for _ in range(ITERATIONS):
        J = _jacobian(prob, X, coef, centre, M @ coef)[:, :n_free]
        A = np.column_stack([J, prob.offsets, M])
        step = np.linalg.lstsq(A, r, rcond=None)[0][:n_free]
        X_new = _perturb(X, step[:6], centre)
        old = prob.sigma_px, prob.stretch.copy()
        prob.sigma_px = float(np.clip(prob.sigma_px + step[6], 0.5 * sigma0, 1.5 * sigma0))
        if n_free > 7:
            prob.stretch = np.clip(prob.stretch + step[7:9], -MAX_STRETCH, MAX_STRETCH)
        M_new = prob.columns(X_new)
        coef_new, r_new = prob.linear(M_new)
        ssr_new = float(r_new @ r_new)
        if not ssr_new < ssr:
            prob.sigma_px, prob.stretch = old
            break
        X, M, coef, r, ssr = X_new, M_new, coef_new, r_new, ssr_new
        if math.degrees(float(np.linalg.norm(step[:3]))) < DONE_DEG and float(np.linalg.norm(step[3:6])) < DONE_MM:
            break
    J = _jacobian(prob, X, coef, centre, M @ coef)[:, :n_free]
    A = np.column_stack([J, prob.offsets, M])
    dof = max(prob.y.size - A.shape[1], 1)
    try:
        N_inv = np.linalg.inv(A.T @ A)
    except np.linalg.LinAlgError:
        return X, None
    # the sandwich (heteroscedasticity-robust) covariance: a magnitude image's noise is smaller in the background
    # (Rayleigh, 0.66 sigma) than on the fluid (sigma), where the pose's information is; one pooled variance would
    # understate the error by up to 1.5x (measured), the pixels' own squared residuals do not
    meat = (A * (r * r)[:, None]).T @ A
    cov = ((N_inv @ meat @ N_inv) * (prob.y.size / dof))[:n_free, :n_free]
    sd = np.sqrt(np.maximum(np.diag(cov)[7:9], 0.0)) if n_free > 7 else np.zeros(2)
    return X, (cov, sd, math.sqrt(ssr / dof))


def spread_slices(n_slices: int, n_max: int = BLURRED_MAX_SLICES) -> list[int]:
    """Indices of at most ``n_max`` of ``n_slices`` slices, spread evenly; the two end slices (which may cut the
    tubes' ends) only when there are no more than ``n_max + 1``."""
    if n_slices <= n_max:
        return list(range(n_slices))
    if n_slices == n_max + 1:
        return list(range(n_max))
    return sorted({int(round(v)) for v in np.linspace(0, n_slices - 1, n_max + 2)[1:-1]})


def blurred_stage(model: TubeModel, fit, seen: list[DetectedSlice], max_slices: int = BLURRED_MAX_SLICES):
    """``(fit, precision, blurred)``: the solver's pose (a ``refine._Fit``) refitted through the blurred model (on
    at most ``max_slices`` of the slices, :func:`spread_slices`), with
    its 1-sigma ``(TRE mm, rotation deg)`` and the :class:`BlurredFit` (point spread, residual noise);
    ``(fit, None, None)`` unchanged (``(fit, None, BlurredFit)`` when it moved too far) when no fit is possible or the pixel fit lands more
    than 1 mm or 1 degree from the blob pose (something in the boxes the model does not have: tissue, another
    object; the blobs' pose then stands, judged as it is). A significant stretch of the image (a wrong pixel
    spacing) raises :class:`~chic_register.errors.NoLock`."""
    xys = [d.xy_mm for d in seen]
    slices = [d.slice for d in seen]
    Ss = [d.T_scanner_from_image for d in seen]
    blob_sets = [d.blobs for d in seen]
    pick = spread_slices(len(slices), max_slices)
    blurred = blurred_fit(model, fit.T_F_from_scanner, [slices[j] for j in pick], [Ss[j] for j in pick],
                          [blob_sets[j] for j in pick], [fit.assignments[j] for j in pick])
    if blurred is None:
        return fit, None, None
    stretch, sd = np.array(blurred.stretch), np.array(blurred.stretch_sd)
    worst = int(np.argmax(np.abs(stretch)))
    if abs(stretch[worst]) > STRETCH_MIN and abs(stretch[worst]) > STRETCH_SIGMAS * sd[worst]:
        axis = ("columns (x)", "rows (y)")[worst]
        raise NoLock(f"the pixels fit best with the image stretched {100 * stretch[worst]:+.1f} % along its {axis} "
                     f"({abs(stretch[worst]) / max(sd[worst], 1e-12):.1f} sigma): the pixel spacing looks wrong; "
                     f"check --pixel-spacing or the file's PixelSpacing",
                     {"stretch": [round(float(v), 4) for v in stretch], "residual_sigma": round(blurred.noise_sigma, 6)})
    if poses_distinct(blurred.T_F_from_scanner, fit.T_F_from_scanner, model):
        return fit, None, blurred
    moved = refine(model, xys, Ss, blurred.T_F_from_scanner, gates_mm=(), final_iters=0,
                   assign0=fit.assignments)  # the blob residuals at the pose, for the report
    return (dataclasses.replace(moved, T_F_from_scanner=blurred.T_F_from_scanner), blurred.precision(model.length_mm),
            blurred)
