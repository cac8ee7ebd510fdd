"""The uncertainty of a registered pose: its covariance, from the solver's own estimator.

The solver's pose is the least-squares fit (Gauss-Newton, unweighted) of the
model's tube positions to the measured ones (intensity centroids of each
blob's footprint, :mod:`chic_register.detect.blobs`). Its covariance to first order
is the sandwich ``H^-1 J^T S J H^-1`` (``H = J^T J``) where ``J`` is the fit's
Jacobian at the solution and ``S`` the block-diagonal covariance of the
measured positions. A centroid is linear in the pixels, so its 2x2
covariance follows from the pixel noise: ``sum_i var_i (x_i - c)(x_i - c)^T / W^2``
over the footprint (``W`` the summed weight).

The pixel noise is estimated from the image background: a magnitude image
has a Rayleigh background of scale ``sigma`` (median ``1.1774 sigma``);
otherwise (a Gaussian background with an offset) ``sigma`` is its
interquartile range over 1.349. Each pixel's variance is the Rician variance
at its estimated signal (0.43 ``sigma^2`` in the background, ``sigma^2`` in the
fluid). The residuals then check the noise model: their chi-square per degree
of freedom (``2 N - 6``) under the predicted position covariances; when it is
improbably large (above its 99th percentile), the covariance is scaled up by
it, so a model misfit widens the reported uncertainty instead of hiding.

A section fit's positions also carry the section model's own error on images
it did not draw (:data:`MODEL_ERROR_PX`), a floor that the pixel noise alone
would leave out at high SNR.

The covariance is reported for the perturbation ``delta`` of
:data:`chic_register.model.pose_params.PARAMETER_ORDER` (rotation about F's axes in deg,
then translation along them in mm): the fiducial's points ``p`` (F) move by
``r x p + t``, i.e. ``T_scanner_from_fiducial @ exp(delta)``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from chic_register.detect.blobs import median
from chic_register.detect.detected import DetectedSlice
from chic_register.detect.noise import (
    NoiseEstimate,
    slice_noise,
)
from chic_register.fit.refine import scanner_crossing_jacobian, whitened_residuals
from chic_register.model.pose import invert
from chic_register.model.pose_params import (
    PARAMETER_FRAME,
    PARAMETER_ORDER,
    default_target,
    deg_mm_scale,
    tre_rms_mm,
)
from chic_register.model.tube_model import adjoint, plane_crossings

#: The section model's own error on a fitted tube position, per coordinate, in pixels: on slices rendered from the
#: printed body's mesh through k-space (:mod:`chic_register.studies.kspace`: Gibbs ringing, a sinc pulse's slice
#: profile, a scanner's k-space filter) its noise-free positions sit 0.0004-0.003 mm (0.001-0.006 px) off a rigid
#: pose, and this floor, added to each position's noise covariance, calibrates the covariance there at SNR 10-50
#: (``benchmarks/bench_independent.py``); at SNR 20 it adds ~5 % to a position's variance.
MODEL_ERROR_PX = 0.004


@dataclass(frozen=True)
class PoseUncertainty:
    """Covariance (6x6, :data:`PARAMETER_ORDER`, deg and mm) of a registered pose and what it came from.

    ``residual_chi2_per_dof``: the residuals' chi-square over ``dof`` under
    the predicted position covariances (about 1 when the noise model
    holds); ``inflation``: the factor applied to the covariance (1, or that
    chi-square when improbably large); ``predicted_tre_mm``: RMS 3-D error of
    ``target_F_mm``.
    """

    covariance: np.ndarray
    noise: tuple[NoiseEstimate, ...]
    residual_chi2_per_dof: float
    dof: int
    inflation: float
    target_F_mm: tuple[float, float, float]
    predicted_tre_mm: float
    measurement: str = "centroid"

    def to_dict(self) -> dict:
        return {
            "covariance": {"parameters": list(PARAMETER_ORDER), "frame": PARAMETER_FRAME,
                           "matrix": [[float(v) for v in row] for row in self.covariance]},
            "noise": {"image_sigma": [round(n.sigma, 6) for n in self.noise],
                      "background_model": [n.model for n in self.noise],
                      "background_pixels": [n.n_pixels for n in self.noise],
                      "measurement": self.measurement,
                      "residual_chi2_per_dof": round(self.residual_chi2_per_dof, 4), "dof": self.dof,
                      "inflation": round(self.inflation, 4)},
            "target_F_mm": [float(v) for v in self.target_F_mm],
            "predicted_tre_mm": round(self.predicted_tre_mm, 6),
        }

    def widened(self, extra: np.ndarray, why: str) -> PoseUncertainty:
        """This uncertainty with ``extra`` (6, 6, the same parameters) added to its covariance (a parameter fitted
        with the pose, as the image's scale), the predicted TRE recomputed; ``why`` joins the measurement's name."""
        cov = self.covariance + 0.5 * (extra + extra.T)
        return dataclasses.replace(self, covariance=cov, predicted_tre_mm=tre_rms_mm(cov, self.target_F_mm),
                                   measurement=f"{self.measurement} + {why}")


#: Signal over sigma of :data:`RICIAN_VARIANCE`'s entries: 0 to 8 in steps of 0.05 (beyond 8 the factor is 1 within 1e-2).
RICIAN_SIGNAL = np.linspace(0.0, 8.0, 161)
#: The variance of a Rician magnitude (sigma 1) at each :data:`RICIAN_SIGNAL`, by the trapezoid rule over its density
#: ``x exp(-(x^2 + a^2) / 2) I0(a x)`` on 4001 points of [0, 20] (:func:`rician_variance_by_quadrature` computes it
#: again; a one-shot volume solve would spend 30-50 ms on it).
RICIAN_VARIANCE = np.array([
    0.4291971281917737, 0.4297333261187808, 0.43133824605102133, 0.4340009122475248, 0.43770318364268546,
    0.4424199786516545, 0.4481195840763612, 0.4547640424649553, 0.4623096109067024, 0.47070728304509624,
    0.4799033650907816, 0.48984009583369126, 0.5004563001044691, 0.5116880648261506, 0.5234694267282982,
    0.5357330609610598, 0.5484109602332028, 0.561435094687806, 0.5747380434989124, 0.5882535900950381,
    0.6019172739613712, 0.6156668931100056, 0.6294429525045846, 0.6431890549501467, 0.6568522321801753,
    0.670383215062182, 0.6837366429749592, 0.6968712134622708, 0.7097497742208825, 0.7223393603207389,
    0.7346111802712607, 0.7465405551342035, 0.7581068153372819, 0.7692931601657151, 0.7800864851049383,
    0.7904771822844667, 0.800458919240123, 0.8100284010804195, 0.819185120926357, 0.8279311032050662,
    0.8362706440310399, 0.8442100525176759, 0.8517573964400418, 0.858922255229488, 0.8657154828340596,
    0.8721489825352702, 0.8782354953814036, 0.8839884034871499, 0.8894215490657, 0.8945490697067244,
    0.8993852500958344, 0.9039443900898272, 0.9082406888187542, 0.9122881442800406, 0.9161004677215168,
    0.9196910119762496, 0.9230727128123775, 0.9262580422907902, 0.9292589730815948, 0.932086952672222,
    0.9347528864035919, 0.9372671282919711, 0.9396394786306654, 0.9418791874135817, 0.943994962680522,
    0.9459949829476297, 0.9478869129550258, 0.9496779220343523, 0.951374704469865, 0.9529835012977621,
    0.9545101230559663, 0.955959973062587, 0.9573380708622139, 0.9586490755368953, 0.95989730863087,
    0.9610867764859616, 0.9622211918275436, 0.963303994478764, 0.9643383711141347, 0.9653272739924894,
    0.9662734386340261, 0.967179400426577, 0.9680475101642436, 0.9688799485344184, 0.9696787395816564,
    0.9704457631843688, 0.9711827665874608, 0.9718913750382079, 0.9725731015757155, 0.9732293560257759,
    0.9738614532536829, 0.9744706207264677, 0.9750580054358586, 0.9756246802304815, 0.9761716496046056,
    0.9766998549877712, 0.9772101795774226, 0.9777034527536621, 0.9781804541127954, 0.9786419171536345,
    0.9790885326476371, 0.9795209517217423, 0.9799397886800278, 0.9803456235884376, 0.9807390046443061,
    0.9811204503504847, 0.9814904515121761, 0.9818494730729235, 0.9821979558042742, 0.9825363178625324,
    0.9828649562247556, 0.9831842480148403, 0.9834945517291018, 0.9837962083711531, 0.9840895425026588,
    0.9843748632186333, 0.9846524650525339, 0.9849226288179622, 0.9851856223916684, 0.9854417014428662,
    0.9856911101134287, 0.9859340816523883, 0.9861708390088708, 0.9864015953863969, 0.9866265547614859,
    0.9868459123695246, 0.9870598551600409, 0.9872685622239104, 0.987472205194166, 0.9876709486228208,
    0.9878649503350303, 0.9880543617620958, 0.9882393282552044, 0.9884199893809509, 0.9885964791996003,
    0.9887689265280386, 0.9889374551873686, 0.9891021842371615, 0.9892632281964993, 0.9894206972530526,
    0.9895746974608954, 0.9897253309274063, 0.9898726959905986, 0.9900168873868083, 0.9901579964096996,
    0.9902961110612054, 0.990431316194389, 0.9905636936492215, 0.9906933223814391, 0.9908202785850264,
    0.9909446358083045, 0.9910664650648471, 0.9911858349383635, 0.9913028116827292, 0.9914174593174749,
    0.9915298397180976, 0.9916400127026677, 0.9917480361139965, 0.9918539658981018, 0.9919578561790274,
    0.9920597593299476
])


def rician_variance_by_quadrature(a: np.ndarray) -> np.ndarray:
    """The variance of a Rician magnitude (sigma 1) at signals ``a`` (N,), by quadrature of its density."""
    x = np.linspace(0.0, 20.0, 4001)
    var = np.empty(np.shape(a))
    for i, ai in enumerate(np.asarray(a, float)):
        p = x * np.exp(-0.5 * (x * x + ai * ai)) * np.i0(ai * x)
        mean = np.trapezoid(p * x, x) / np.trapezoid(p, x)
        var[i] = 2.0 + ai * ai - mean * mean
    return var


def rician_variance_factor(a) -> np.ndarray:
    """Variance of a Rician magnitude over sigma^2 at signal/sigma ``a`` (2 - pi/2 at 0, -> 1 at high signal)."""
    return np.interp(np.abs(np.asarray(a, dtype=float)), RICIAN_SIGNAL, RICIAN_VARIANCE, right=1.0)


def centroid_covariance(pixels: np.ndarray, footprint, background: float, noise: NoiseEstimate,
                        pixel_spacing_mm) -> np.ndarray:
    """2x2 covariance (image x = columns, y = rows; mm^2) of the background-subtracted intensity centroid of a footprint."""
    r0, c0, mask = footprint
    h, w = mask.shape
    z = np.asarray(pixels[r0:r0 + h, c0:c0 + w], dtype=float)
    wgt = np.where(mask, z - background, 0.0)
    total = float(wgt.sum())
    if not total > 0:
        return np.full((2, 2), np.inf)
    rr, cc = np.nonzero(mask)
    wv = wgt[rr, cc]
    mr, mc = float(wv @ rr) / total, float(wv @ cc) / total
    s2 = noise.sigma ** 2
    if noise.model == "rayleigh" and noise.sigma > 0:
        nu = np.sqrt(np.maximum(z[rr, cc] ** 2 - 2.0 * s2, 0.0)) / noise.sigma
        var = s2 * rician_variance_factor(nu)
    else:
        var = np.full(rr.size, s2)
    rs, cs = (float(v) for v in pixel_spacing_mm)
    d = np.stack([(cc - mc) * cs, (rr - mr) * rs])  # (2, n): x, y in mm
    return (d * var) @ d.T / (total * total)


def _binomial_passes(x: np.ndarray, n: int) -> np.ndarray:
    """``n`` separable [1, 2, 1] / 4 passes over the last two axes, edges replicated (the detector's smoothing)."""
    for _ in range(n):
        for ax in (-2, -1):
            pad = [(0, 0)] * x.ndim
            pad[ax] = (1, 1)
            p = np.pad(x, pad, mode="edge")
            m = x.shape[ax]
            x = 0.25 * (np.take(p, range(0, m), ax) + 2 * np.take(p, range(1, m + 1), ax) + np.take(p, range(2, m + 2), ax))
    return x


def _grow(m: np.ndarray) -> np.ndarray:
    """3 x 3 binary dilation over the last two axes."""
    p = np.pad(m, [(0, 0)] * (m.ndim - 2) + [(1, 1), (1, 1)])
    h, w = m.shape[-2:]
    out = np.zeros_like(m)
    for dr in range(3):
        for dc in range(3):
            out |= p[..., dr:dr + h, dc:dc + w]
    return out


def mask_jitter_covariances(pixels: np.ndarray, footprints, which, threshold: float, noise: NoiseEstimate,
                            pixel_spacing_mm, tube_diameter_mm: float, *, background: float = 0.0,
                            draws: int = 16, seed: int = 0) -> np.ndarray:
    """2x2 covariances (len(which), 2, 2; mm^2) the centroids of blobs ``which`` gain because their footprints
    themselves depend on the noise.

    The detector's footprint is the smoothed image above its threshold, grown
    by one pixel (:func:`chic_register.detect.blobs.detect_blobs`); where a
    section's edge is a long shallow ramp (a tube crossing the slab
    obliquely) pixels enter and leave it with the noise, and the pixels that
    enter are the brighter ones: for such sections this adds about as much
    variance as the pixels' own noise. Measured by a parametric bootstrap on
    each blob's patch (all blobs at once): ``draws`` fresh noise fields (each
    pixel's variance as in :func:`centroid_covariance`) added to the patch,
    which is smoothed, thresholded and grown as the detector does (kept off
    the other blobs' footprints); the centroid over that footprint against
    the centroid over the original one, under the same noise (a control
    variate), gives the footprint's share. Seeded: the same image gives the
    same answer.
    """
    which = [int(i) for i in which]
    if not which:
        return np.zeros((0, 2, 2))
    img = np.asarray(pixels, dtype=float)
    H, W = img.shape
    pad = 2
    hc = max(footprints[i][2].shape[0] for i in which) + 2 * pad
    wc = max(footprints[i][2].shape[1] for i in which) + 2 * pad
    patches = np.empty((len(which), hc, wc))
    own = np.zeros((len(which), hc, wc), bool)
    near = np.zeros((len(which), hc, wc), bool)
    for t, i in enumerate(which):
        r0, c0, m = footprints[i]
        R0, C0 = r0 - pad, c0 - pad  # the patch's first pixel (may lie outside the image: edges replicated)
        rows = np.clip(np.arange(R0, R0 + hc), 0, H - 1)
        cols = np.clip(np.arange(C0, C0 + wc), 0, W - 1)
        patches[t] = img[rows[:, None], cols[None, :]]
        own[t, pad:pad + m.shape[0], pad:pad + m.shape[1]] = m
        free = np.ones((hc, wc), bool)
        for n, (o0, p0, om) in enumerate(footprints):  # never into a neighbour's footprint
            if n == i or o0 >= R0 + hc or p0 >= C0 + wc or o0 + om.shape[0] <= R0 or p0 + om.shape[1] <= C0:
                continue
            a0, b0 = max(o0, R0), max(p0, C0)
            a1, b1 = min(o0 + om.shape[0], R0 + hc), min(p0 + om.shape[1], C0 + wc)
            free[a0 - R0:a1 - R0, b0 - C0:b1 - C0] &= ~om[a0 - o0:a1 - o0, b0 - p0:b1 - p0]
        near[t] = _grow(own[t]) & (free | own[t])
    rs, cs = (float(v) for v in pixel_spacing_mm)
    r_px = 0.5 * tube_diameter_mm / math.sqrt(rs * cs)
    sig = max(0.5, 0.3 * r_px)  # the detector's default smoothing: round(2 sig^2) binomial passes
    passes = min(3, max(1, int(round(2 * sig * sig))))
    sd = noise.sigma * np.sqrt(_pixel_variance_factor(patches, noise))
    rng = np.random.default_rng(seed)
    imgs = patches[:, None] + rng.normal(0.0, 1.0, (len(which), int(draws), hc, wc)) * sd[:, None]
    feet = _grow((_binomial_passes(imgs, passes) > threshold) & near[:, None]) & near[:, None]
    rr, cc = np.mgrid[0:hc, 0:wc]
    z = imgs - background

    def centroids(wgt):
        total = wgt.sum(axis=(2, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.stack([(wgt * cc).sum(axis=(2, 3)) / total * cs, (wgt * rr).sum(axis=(2, 3)) / total * rs], -1)

    full, fixed = centroids(np.where(feet, z, 0.0)), centroids(np.where(own[:, None], z, 0.0))
    out = np.zeros((len(which), 2, 2))
    for t in range(len(which)):
        ok = np.all(np.isfinite(full[t]), axis=1) & np.all(np.isfinite(fixed[t]), axis=1)
        if ok.sum() < 3:
            continue
        # cov(full) - cov(fixed) = cov(d) + cov(d, fixed) + cov(fixed, d), d = full - fixed
        d, f = full[t, ok] - fixed[t, ok], fixed[t, ok] - fixed[t, ok].mean(axis=0)
        d = d - d.mean(axis=0)
        C = (d.T @ d + d.T @ f + f.T @ d) / (len(d) - 1)
        out[t] = 0.5 * (C + C.T)  # unclipped: a noisy estimate of a share near 0 stays unbiased
    return out


def _pixel_variance_factor(z: np.ndarray, noise: NoiseEstimate) -> np.ndarray:
    """Each pixel's noise variance over sigma^2: Rician at its estimated signal, or 1 (Gaussian)."""
    if noise.model == "rayleigh" and noise.sigma > 0:
        nu = np.sqrt(np.maximum(z * z - 2.0 * noise.sigma ** 2, 0.0)) / noise.sigma
        return rician_variance_factor(nu)
    return np.ones_like(z)


def sandwich(J: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Covariance of the unweighted least-squares estimate ``(J^T J)^-1 J^T m`` when ``m`` has covariance ``S``."""
    Hinv = np.linalg.inv(J.T @ J)
    return Hinv @ J.T @ S @ J @ Hinv


def residual_chi2(residuals: np.ndarray, S: np.ndarray, J: np.ndarray) -> tuple[float, int]:
    """Chi-square per degree of freedom of least-squares residuals (M,) with measurement covariance ``S`` (M, M)."""
    M, p = J.shape
    dof = M - p
    if dof <= 0:
        return float("nan"), dof
    # the residual's covariance is (I - P) S (I - P), P the hat matrix; its pseudo-inverse weighs them
    P = J @ np.linalg.solve(J.T @ J, J.T)
    R = (np.eye(M) - P) @ S @ (np.eye(M) - P)
    chi2 = float(residuals @ np.linalg.pinv(R, rcond=1e-10, hermitian=True) @ residuals)
    return chi2 / dof, dof


def inflation_factor(chi2_per_dof: float, dof: int, p: float = 0.99) -> float:
    """1 when the residuals fit the noise model; their chi-square per dof when it exceeds its ``p`` quantile."""
    if not (dof > 0 and math.isfinite(chi2_per_dof)):
        return 1.0
    return chi2_per_dof if chi2_per_dof > chi2_quantile(p, dof) / dof else 1.0


def normal_quantile(p: float) -> float:
    """The standard normal ``p`` quantile, 0 < p < 1: Newton's method on ``math.erfc``.

    Not ``statistics.NormalDist`` (it pulls ``fractions`` in: ~4 ms on every one-shot solve). For p > 1/2 the
    CDF is concave, so Newton from 0 rises monotonically onto the root; p < 1/2 by symmetry.
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"a quantile needs 0 < p < 1, got {p!r}")
    if p < 0.5:
        return -normal_quantile(1.0 - p)
    z = 0.0
    for _ in range(100):
        step = (0.5 * math.erfc(-z / math.sqrt(2.0)) - p) / (math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi))
        z -= step
        if abs(step) < 1e-12 * max(1.0, z):
            break
    return z


def chi2_quantile(p: float, dof: int) -> float:
    """Chi-square quantile (Wilson-Hilferty; within 1 % for dof >= 3), without importing scipy.stats."""
    z = normal_quantile(p)
    c = 2.0 / (9.0 * dof)
    return dof * (1.0 - c + z * math.sqrt(c)) ** 3


def target_point(geom, target_F_mm=None) -> tuple[float, float, float]:
    """The TRE target: given, else the geometry's tool tip, else the body's centre on the axis (see :func:`chic_register.model.pose_params.default_target`)."""
    if target_F_mm is not None:
        return tuple(float(v) for v in target_F_mm)
    return default_target(geom)


def pose_uncertainty(J_F: np.ndarray, S: np.ndarray, residuals: np.ndarray, noise, target_F_mm,
                     measurement: str = "centroid") -> PoseUncertainty:
    """Covariance of a point-fit pose: ``J_F`` (M, 6) d(predicted positions)/d(delta) in (rad, mm),
    ``S`` (M, M) the measured positions' covariance, ``residuals`` (M,) predicted minus measured."""
    C = sandwich(J_F, S)
    chi, dof = residual_chi2(residuals, S, J_F)
    k = inflation_factor(chi, dof)
    cov = k * C * np.outer(deg_mm_scale(), deg_mm_scale())
    cov = 0.5 * (cov + cov.T)
    target = tuple(float(v) for v in target_F_mm)
    return PoseUncertainty(cov, tuple(noise), chi, dof, k, target, tre_rms_mm(cov, target), measurement)


def pixel_fit_uncertainty(blurred, seen: list[DetectedSlice], target_F_mm) -> PoseUncertainty:
    """The uncertainty of a pose fitted to the pixels through the blurred model (a
    :class:`chic_register.fit.blurred.BlurredFit`): its sandwich covariance, in F's parameters. The residual
    chi-square per degree of freedom is the fit's residual variance over the background's."""
    noises = tuple(slice_noise(d.slice, d.blobs.footprints) for d in seen)
    bg = float(np.mean([n.sigma for n in noises]))
    chi = (blurred.noise_sigma / bg) ** 2 if bg > 0 else float("nan")
    cov = blurred.covariance_F()
    target = tuple(float(v) for v in target_F_mm)
    return PoseUncertainty(cov, noises, chi, max(int(blurred.n_pixels) - 7, 1), 1.0, target, tre_rms_mm(cov, target),
                           "blurred fit (pixels)")


def mahalanobis2(delta_deg_mm: np.ndarray, covariance: np.ndarray) -> float:
    """Squared Mahalanobis length of a pose error (order :data:`PARAMETER_ORDER`) under a covariance."""
    d = np.asarray(delta_deg_mm, dtype=float)
    return float(d @ np.linalg.solve(covariance, d))


def detection_diameter_mm(blobs, model) -> float:
    """The tube diameter the detector smoothed for: the geometry's median, or the width it measured in the
    image when that differs by more than a quarter (:func:`chic_register.detect.blobs.detect_blobs` redoes the
    detection at that size)."""
    d_mid = median(model.diameter_mm)
    width = float(getattr(blobs, "width_mm", float("nan")))
    if math.isfinite(width) and not 0.8 <= width / d_mid <= 1.25:
        return width
    return d_mid


def registration_uncertainty(model, fit, seen: list[DetectedSlice], target_F_mm,
                             measurement: str = "centroid") -> PoseUncertainty:
    """The covariance of a solver fit (``chic_register.pipeline.register``): its Jacobian at the solution, the measured
    positions' covariances, and the residuals' check.

    ``fit`` holds ``T_F_from_scanner``, per-slice ``assignments`` (tube -> blob index or -1) and, when its
    positions were not the blob centroids, ``measurements``: per slice (positions (N, 2) mm, square-root
    information ``L`` (K, 2, 2) the fit was weighted by, the noise sigma ``L`` assumed); ``seen``: the slices
    with their blobs (the blob centroids are the positions otherwise).
    """
    xys = [d.xy_mm for d in seen]
    X = fit.T_F_from_scanner
    Ad_sf = adjoint(invert(X))
    meas = getattr(fit, "measurements", None)
    Js, rs, blocks, noises = [], [], [], []
    for j, d in enumerate(seen):
        sl, S, b = d.slice, d.T_scanner_from_image, d.blobs
        noise = slice_noise(sl, b.footprints)
        noises.append(noise)
        a = fit.assignments[j]
        q, tan, _, inside = plane_crossings(model, X @ S, margin_mm=1e-9)
        k = np.flatnonzero((a >= 0) & inside)
        if k.size == 0:
            continue
        J_s = scanner_crossing_jacobian(q[k], tan[k], S)  # d/d(xi) of X @ exp(xi), xi in the scanner
        J_F = -J_s @ Ad_sf  # the same motion as delta in F: xi = -Ad(T_sf) delta
        if meas is not None:  # an information-weighted fit of fitted section positions (the default mode)
            _, L, sigma_used = meas[j]
            Js.append(np.einsum("kij,kjl->kil", L[k], J_F).reshape(-1, 6))
            rs.append(whitened_residuals(meas[j], q, a, k).ravel())
            # L whitens the positions for the noise sigma it assumed; the image's own sigma rescales that
            scale = (noise.sigma / sigma_used) ** 2 if sigma_used > 0 else 1.0
            floor = (MODEL_ERROR_PX * float(min(sl.pixel_spacing_mm))) ** 2  # in the whitened positions: L L^T
            blocks += [scale * np.eye(2) + floor * (L[i] @ L[i].T) for i in k]
            continue
        Js.append(J_F.reshape(-1, 6))
        rs.append((q[k] - xys[j][a[k]]).ravel())
        jitter = mask_jitter_covariances(sl.pixels, b.footprints, a[k], b.threshold, noise, sl.pixel_spacing_mm,
                                         detection_diameter_mm(b, model), background=b.background, seed=j)
        for i, extra in zip(a[k], jitter):
            base = centroid_covariance(sl.pixels, b.footprints[int(i)], b.background, noise, sl.pixel_spacing_mm)
            vals, vecs = np.linalg.eigh(base + extra)  # never below the fixed footprint's own half
            floor = 0.5 * float(np.linalg.eigvalsh(base)[0])
            blocks.append((vecs * np.maximum(vals, floor)) @ vecs.T)
    J = np.concatenate(Js)
    S = np.zeros((J.shape[0], J.shape[0]))
    for n, B in enumerate(blocks):
        S[2 * n:2 * n + 2, 2 * n:2 * n + 2] = B
    return pose_uncertainty(J, S, np.concatenate(rs), noises, target_F_mm,
                            "section fit" if meas is not None else measurement)


def _matched_rows(model, fit, seen: list[DetectedSlice]):
    """Per slice with matched tubes: ``(j, k, q, J)``: the slice, its matched tubes inside it, their crossings (K_j,
    2; image mm), and the crossings'
    Jacobian (2 rows per tube, 6 columns: d(predicted position)/d(delta) in (rad, mm) of F's parameters)."""
    X = fit.T_F_from_scanner
    Ad_sf = adjoint(invert(X))
    rows = []
    for j, d in enumerate(seen):
        a = fit.assignments[j]
        q, tan, _, inside = plane_crossings(model, X @ d.T_scanner_from_image, margin_mm=1e-9)
        k = np.flatnonzero((a >= 0) & inside)
        if k.size:
            J_s = scanner_crossing_jacobian(q[k], tan[k], d.T_scanner_from_image)
            rows.append((j, k, q[k], (-J_s @ Ad_sf).reshape(-1, 6)))
    return rows


def scatter_uncertainty(model, fit, seen: list[DetectedSlice], sigma_mm: list[np.ndarray], target_F_mm,
                        measurement: str = "centroid + model error") -> PoseUncertainty:
    """The covariance of an unweighted centroid fit whose matched centres scatter by ``sigma_mm`` (per slice, (K,)
    per tube, per coordinate, mm; NaN where unmatched): each centre's image noise and the model error the
    residuals show (:class:`chic_register.fit.scatter.Scatter`), rather than the noise alone."""
    noises = [slice_noise(d.slice, d.blobs.footprints) for d in seen]
    Js, rs, var = [], [], []
    for j, k, q, J in _matched_rows(model, fit, seen):
        Js.append(J)
        rs.append((q - seen[j].xy_mm[fit.assignments[j][k]]).ravel())
        var.append(np.repeat(np.asarray(sigma_mm[j], float)[k] ** 2, 2))
    J = np.concatenate(Js)
    return pose_uncertainty(J, np.diag(np.concatenate(var)), np.concatenate(rs), noises, target_F_mm, measurement)


def position_covariance(model, fit, seen: list[DetectedSlice], sigma_mm: float) -> np.ndarray:
    """(6, 6) in F's parameters (deg, mm): the pose's covariance when each matched section lies ``sigma_mm`` (per
    coordinate) from where the pose puts it, whatever else the fit measured (a pose fitted to the pixels: its
    sections' model error, :func:`chic_register.verify.pixels.section_model_error_mm`)."""
    J = np.concatenate([J for *_, J in _matched_rows(model, fit, seen)])
    C = sigma_mm * sigma_mm * np.linalg.inv(J.T @ J) * np.outer(deg_mm_scale(), deg_mm_scale())
    return 0.5 * (C + C.T)
