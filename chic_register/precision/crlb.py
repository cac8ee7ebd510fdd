"""Cramer-Rao lower bound (CRLB) of the fiducial's pose from its MRI slices.

What the best unbiased estimator could reach, for a design and an imaging
protocol, from the pixels themselves (not from detected centres):

- image model: the simulator's noise-free fluid-fraction image
  (:func:`chic_register.imaging.render.render_slice`: partial volume over the pixel
  and the slice thickness) times an unknown fluid gain ``g`` (a nuisance
  parameter, 1 at the truth), plus magnitude noise: Rician of scale
  ``sigma = 1 / snr`` (the simulator's ``add_rician_noise``), or Gaussian;
- parameters: the fiducial's pose perturbation ``delta = (rx, ry, rz, tx, ty, tz)``,
  a small rotation about F's axes through F's origin and a translation along
  F's axes (every point ``p`` of F moves by ``r x p + t``), plus ``g``;
- Fisher information ``F = sum_pixels w(mu / sigma) / sigma^2 * dmu dmu^T``:
  ``dmu`` by central differences of the rendered image (smooth: the renderer
  anti-aliases every edge), ``w = 1`` for Gaussian noise and the Rician
  information factor (0 in the background, 1 at high signal) for Rician;
- several parallel slices (``Protocol.n_slices`` at ``slice_spacing_mm``,
  centred on the given depth) add their information; the gain is shared.

The bound is ``inv(F)`` restricted to the pose (the gain marginalised out).
It is reported as the 6x6 covariance (order :data:`PARAMETER_ORDER`, degrees
and mm) and as the RMS errors the study reports: normal-vector angle, twist
and depth (:func:`chic_register.model.pose.slice_angles`), and the target
registration error (TRE) at a point of F.

Speed (measured on the 2-core test machine under a load average of ~2.5,
one thread): :func:`pose_crlb` of one 2 mm ``neuro`` slice takes about
0.25 s CPU with the default sampling (4x4 samples per pixel, 5 sub-planes)
and about 0.1 s with ``quality="fast"`` (3x3, 3 sub-planes; within a few
per cent of the default); a precision map of D depths x T tilts x A azimuths
costs D*T*A such calls.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field

import numpy as np

from chic_register.imaging.render import render_slice
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import rigid, slice_angles, slice_frame, wrap_deg
from chic_register.model.pose_params import (
    PARAMETER_FRAME,
    PARAMETER_ORDER,
    default_target,
    deg_mm_scale,
    target_jacobian,
    tre_rms_mm,
)

NOISE_MODELS = ("rician", "gaussian")
#: Sampling of the renderer: (supersample, thickness_samples).
QUALITY = {"default": (4, 5), "fast": (3, 3)}
STEP_RAD = 1e-3  # central-difference steps: ~0.03 mm at the tubes for rotations
STEP_MM = 0.02


@dataclass(frozen=True)
class Protocol:
    """The imaging protocol the bound is for.

    ``pixel_size_mm``: square in-plane pixels; ``slice_thickness_mm``: slab
    thickness (0: an ideal thin plane); ``snr``: fluid signal over the noise
    scale ``sigma``; ``n_slices`` parallel slices ``slice_spacing_mm`` apart
    (centre to centre), centred on the pose's depth; ``noise``: ``"rician"``
    (magnitude images) or ``"gaussian"``.
    """

    pixel_size_mm: float = 0.5
    slice_thickness_mm: float = 2.0
    snr: float = 20.0
    n_slices: int = 1
    slice_spacing_mm: float = 0.0
    noise: str = "rician"

    def __post_init__(self):
        if not (self.pixel_size_mm > 0 and math.isfinite(self.pixel_size_mm)):
            raise ValueError(f"pixel_size_mm must be > 0, got {self.pixel_size_mm}")
        if not (self.slice_thickness_mm >= 0 and math.isfinite(self.slice_thickness_mm)):
            raise ValueError(f"slice_thickness_mm must be >= 0, got {self.slice_thickness_mm}")
        if not (self.snr > 0 and math.isfinite(self.snr)):
            raise ValueError(f"snr must be > 0, got {self.snr}")
        if int(self.n_slices) != self.n_slices or self.n_slices < 1:
            raise ValueError(f"n_slices must be a whole number >= 1, got {self.n_slices}")
        if not (self.slice_spacing_mm >= 0 and math.isfinite(self.slice_spacing_mm)):
            raise ValueError(f"slice_spacing_mm must be >= 0, got {self.slice_spacing_mm}")
        if self.noise not in NOISE_MODELS:
            raise ValueError(f"noise is {self.noise!r}; allowed: {', '.join(NOISE_MODELS)}")

    @property
    def sigma(self) -> float:
        """Noise scale for a fluid signal of 1."""
        return 1.0 / self.snr

    def offsets_mm(self) -> np.ndarray:
        """Offsets of the slices along the image normal from the central plane; shape (n_slices,)."""
        n = int(self.n_slices)
        return (np.arange(n) - (n - 1) / 2.0) * self.slice_spacing_mm

    def to_dict(self) -> dict:
        return {"pixel_size_mm": self.pixel_size_mm, "slice_thickness_mm": self.slice_thickness_mm,
                "snr": self.snr, "n_slices": int(self.n_slices), "slice_spacing_mm": self.slice_spacing_mm,
                "noise": self.noise}


@dataclass(frozen=True)
class PrecisionBound:
    """The CRLB at one pose.

    ``covariance`` (6x6): of the pose perturbation, order
    :data:`PARAMETER_ORDER` (deg, mm) in :data:`PARAMETER_FRAME`;
    ``sd_normal_deg``: RMS angle between the true and estimated image
    normal; ``sd_twist_deg`` / ``sd_depth_mm``: SD of the twist and depth of
    :func:`~chic_register.model.pose.slice_angles`; ``tre_mm``: RMS 3-D error of the
    target point ``target_F_mm``; ``fisher``: the 7x7 information (pose in
    rad and mm, then the gain).
    """

    depth_mm: float
    tilt_deg: float
    azimuth_deg: float
    twist_deg: float
    covariance: np.ndarray
    sd_normal_deg: float
    sd_twist_deg: float
    sd_depth_mm: float
    tre_mm: float
    target_F_mm: tuple[float, float, float]
    protocol: Protocol
    fisher: np.ndarray = field(repr=False, default=None)

    def to_dict(self) -> dict:
        return {
            "depth_mm": self.depth_mm, "tilt_deg": self.tilt_deg, "azimuth_deg": self.azimuth_deg,
            "twist_deg": self.twist_deg, "sd_normal_deg": self.sd_normal_deg,
            "sd_twist_deg": self.sd_twist_deg, "sd_depth_mm": self.sd_depth_mm, "tre_mm": self.tre_mm,
            "target_F_mm": list(self.target_F_mm),
            "covariance": {"parameters": list(PARAMETER_ORDER), "frame": PARAMETER_FRAME,
                           "matrix": np.asarray(self.covariance).tolist()},
        }


# --------------------------------------------------------------------------- noise


@functools.lru_cache(maxsize=1)
def _rician_table():
    """Rician information factor w(a) on a grid of a = signal / sigma (w -> 1 at high a, 0 at a = 0)."""
    from scipy.special import i0e, i1e  # deferred: loads scipy only when used (one-shot start-up)

    a = np.concatenate([np.linspace(0.0, 10.0, 201), np.linspace(10.25, 40.0, 120)])
    w = np.empty_like(a)
    for i, ai in enumerate(a):
        x = np.linspace(max(0.0, ai - 12.0), ai + 12.0, 4001)
        p = x * np.exp(-0.5 * (x - ai) ** 2) * i0e(ai * x)  # Rice density (sigma = 1)
        ratio = i1e(ai * x) / i0e(ai * x)
        w[i] = np.trapezoid(p * (x * ratio) ** 2, x) / np.trapezoid(p, x) - ai * ai
    return a, np.clip(w, 0.0, 1.0)


def rician_information(a) -> np.ndarray:
    """Fisher information of a Rician magnitude about its signal, times sigma^2, at signal/sigma ``a``."""
    grid, w = _rician_table()
    return np.interp(np.abs(np.asarray(a, dtype=float)), grid, w, right=1.0)


def noise_weights(mu: np.ndarray, protocol: Protocol) -> np.ndarray:
    """Per-pixel information weight (over sigma^2) of the noise-free image ``mu``."""
    if protocol.noise == "gaussian":
        return np.ones_like(mu)
    return rician_information(mu / protocol.sigma)


# --------------------------------------------------------------------------- image model


def perturbation(delta) -> np.ndarray:
    """4x4 rigid motion of the fiducial in F for ``delta = (rx, ry, rz (rad), tx, ty, tz (mm))``."""
    from scipy.spatial.transform import Rotation  # deferred: loads scipy only when used (one-shot start-up)

    d = np.asarray(delta, dtype=float)
    return rigid(Rotation.from_rotvec(d[:3]).as_matrix(), d[3:])


def image_shape(geom: FiducialGeometry, T_F_from_S: np.ndarray, protocol: Protocol) -> tuple[int, int]:
    """A square image (pixels) centred on the axis crossing that holds every tube section with margin."""
    T = np.asarray(T_F_from_S, dtype=float)
    n = T[:3, 2]
    half = 0.0
    tz = max(abs(float(n[2])), 0.05)
    for pts in geom.intersect_plane(T[:3, 3], n).values():
        if len(pts):
            s = (pts - T[:3, 3]) @ T[:3, :3]
            half = max(half, float(np.abs(s[:, :2]).max()))
    dmax = max(t.diameter for t in geom.tubes)
    half += dmax / tz + 0.5 * protocol.slice_thickness_mm / tz + 4 * protocol.pixel_size_mm
    half = min(half, 2 * math.hypot(geom.body.length, geom.body.outer_diameter) + 4 * protocol.pixel_size_mm)
    size = int(2 * math.ceil(half / protocol.pixel_size_mm)) + 2
    return size, size


def slice_frames(depth_mm, tilt_deg, azimuth_deg, twist_deg, protocol: Protocol) -> list[np.ndarray]:
    T0 = slice_frame(depth_mm, tilt_deg, azimuth_deg, twist_deg)
    return [T0 @ rigid(np.eye(3), (0.0, 0.0, float(o))) for o in protocol.offsets_mm()]


def model_image(geom: FiducialGeometry, T_F_from_S: np.ndarray, protocol: Protocol, shape, delta=None,
                quality: str = "default") -> np.ndarray:
    """Noise-free image (gain 1) of the slice ``T_F_from_S`` with the fiducial moved by ``delta`` (see :func:`perturbation`)."""
    ss, ts = QUALITY[quality]
    T = np.asarray(T_F_from_S, dtype=float)
    if delta is not None:
        T = np.linalg.inv(perturbation(delta)) @ T
    return render_slice(geom, T, shape=shape, pixel_spacing_mm=(protocol.pixel_size_mm,) * 2,
                        slice_thickness_mm=protocol.slice_thickness_mm, supersample=ss, thickness_samples=ts)


def image_jacobian(geom: FiducialGeometry, T_F_from_S: np.ndarray, protocol: Protocol, shape,
                   quality: str = "default") -> tuple[np.ndarray, np.ndarray]:
    """Noise-free image ``mu`` (rows, cols) and its derivatives (6, rows, cols) w.r.t. delta (rad, mm).

    The central differences turn the fiducial about the slice's centre ``c``
    (where the image normal through the frame origin meets F), not about F's
    origin, then map to delta (a turn ``r`` about ``c`` with a shift ``t'``
    is ``delta = (r, t' + c x r)``): about F's origin a finite turn also
    shifts every section by the lever ``|c|`` (40 mm at 40 mm depth), and the
    step's third-order term (that shift times the second-order change of the
    section shapes) then passes for tilt information. At a normal slice at
    40 mm depth that made the normal-angle bound 0.133 deg instead of 0.225 deg
    (turning about ``c`` the bound changes by < 2 % for steps of 1e-4 to
    3e-3 rad and renderer sampling of 4 or 12).
    """
    from scipy.spatial.transform import Rotation  # deferred: loads scipy only when used (one-shot start-up)

    mu = model_image(geom, T_F_from_S, protocol, shape, quality=quality)
    c = np.asarray(T_F_from_S, dtype=float)[:3, 3]
    Dc = np.empty((6,) + mu.shape)
    for i in range(6):
        h = STEP_RAD if i < 3 else STEP_MM
        imgs = []
        for sign in (1.0, -1.0):
            e = np.zeros(6)
            e[i] = sign * h
            e[3:] += c - Rotation.from_rotvec(e[:3]).as_matrix() @ c  # the turn about c, as a motion in F
            imgs.append(model_image(geom, T_F_from_S, protocol, shape, e, quality))
        Dc[i] = (imgs[0] - imgs[1]) / (2 * h)
    # delta = M (r, t'), M = [[I, 0], [[c]x, I]]: d mu / d delta = M^-T (d mu / d(r, t'))
    skew_c = -target_jacobian(c)[:, :3]
    D = Dc.copy()
    D[:3] -= np.einsum("ji,j...->i...", skew_c, Dc[3:])
    return mu, D


#: Which tubes' sections the bound counts: ``"crossing"``, those whose centreline crosses the slice's
#: central plane within the tube (the sections a solver locates); ``"all"``, also a tube the slab only
#: grazes beyond its end (see :func:`counted_tubes`).
SECTIONS = ("crossing", "all")


def counted_tubes(geom: FiducialGeometry, T_F_from_S: np.ndarray, sections: str = "crossing"):
    """The tubes whose sections the bound counts in the slice ``T_F_from_S`` (see :data:`SECTIONS`).

    A tube whose centreline meets the central plane just beyond its end
    (up to half the slab's reach along it) still leaves a sliver of partial
    volume: at a 45 deg slice near an end face of ``neuro``, 0.3 and 1.3
    pixels of fluid from two tubes, which then carry two thirds of the depth
    information the simulator's image holds. That information is the
    fluid's amount at a sharp planar end face known to ~0.01 mm; the real
    end is a glued cap plate over a printed end face (flatness, glue film,
    a bubble, the fluid in the top cap's fill port), fixed to ~0.1 mm. So
    ``"crossing"`` (the default) counts only the sections of the tubes the
    plane crosses, as the solver uses them (their end faces included where
    they clip a section); ``"all"`` is the idealised simulator's bound.
    """
    if sections not in SECTIONS:
        raise ValueError(f"sections is {sections!r}; allowed: {', '.join(SECTIONS)}")
    if sections == "all":
        return geom.tubes
    T = np.asarray(T_F_from_S, dtype=float)
    hits = geom.intersect_plane(T[:3, 3], T[:3, 2])
    return tuple(t for t in geom.tubes if len(hits[t.id]))


def fisher_information(geom: FiducialGeometry, depth_mm: float, tilt_deg: float, azimuth_deg: float,
                       twist_deg: float, protocol: Protocol, quality: str = "default",
                       sections: str = "crossing") -> np.ndarray:
    """7x7 Fisher information of (delta (rad, mm), gain) from every slice of the protocol (the tubes of
    :func:`counted_tubes`)."""
    F = np.zeros((7, 7))
    s2 = protocol.sigma ** 2
    for T in slice_frames(depth_mm, tilt_deg, azimuth_deg, twist_deg, protocol):
        shape = image_shape(geom, T, protocol)
        tubes = counted_tubes(geom, T, sections)
        mu, D = image_jacobian(geom if len(tubes) == len(geom.tubes) else dataclasses.replace(geom, tubes=tubes),
                               T, protocol, shape, quality)
        G = np.concatenate([D.reshape(6, -1), mu.reshape(1, -1)])  # d(g mu)/d(delta, g) at g = 1
        w = noise_weights(mu, protocol).reshape(-1) / s2
        F += (G * w) @ G.T
    return F


# --------------------------------------------------------------------------- reported errors


def angle_jacobian(T_F_from_S: np.ndarray) -> np.ndarray:
    """d(normal angle components (2), twist, depth)/d(delta) (4x6, rad and mm), numerically on ``slice_angles``."""
    T = np.asarray(T_F_from_S, dtype=float)
    n = T[:3, 2]
    # the normal in the moved fiducial's frame turns by -r x n: its two components across n
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    skew_n = np.array([[0.0, -n[2], n[1]], [n[2], 0.0, -n[0]], [-n[1], n[0], 0.0]])
    J = np.zeros((4, 6))
    J[0, :3] = u @ skew_n  # -(r x n) . u = (n x r) . u
    J[1, :3] = v @ skew_n
    for i in range(6):
        h = 1e-6
        e = np.zeros(6)
        e[i] = h
        ap = slice_angles(np.linalg.inv(perturbation(e)) @ T)
        am = slice_angles(np.linalg.inv(perturbation(-e)) @ T)
        J[2, i] = math.radians(wrap_deg(ap.twist_deg - am.twist_deg)) / (2 * h)
        J[3, i] = (ap.depth_mm - am.depth_mm) / (2 * h)
    return J


def summarise(cov_deg_mm: np.ndarray, T_F_from_S: np.ndarray, target_F_mm) -> dict:
    """RMS normal angle (deg), SD of twist (deg) and depth (mm), TRE (mm) of a pose covariance."""
    s = deg_mm_scale()
    C = np.asarray(cov_deg_mm) / np.outer(s, s)
    J = angle_jacobian(T_F_from_S)
    A = J @ C @ J.T
    return {
        "sd_normal_deg": math.degrees(math.sqrt(max(0.0, A[0, 0] + A[1, 1]))),
        "sd_twist_deg": math.degrees(math.sqrt(max(0.0, A[2, 2]))),
        "sd_depth_mm": math.sqrt(max(0.0, A[3, 3])),
        "tre_mm": tre_rms_mm(cov_deg_mm, target_F_mm),
    }




# --------------------------------------------------------------------------- public API


def pose_crlb(geom: FiducialGeometry, depth_mm: float, tilt_deg: float, azimuth_deg: float = 0.0,
              twist_deg: float = 0.0, protocol: Protocol | None = None, target_F_mm=None, *,
              quality: str = "default", sections: str = "crossing") -> PrecisionBound:
    """The CRLB of the pose of ``geom`` seen in the protocol's slices at this slice pose (:func:`~chic_register.model.pose.slice_frame`).

    ``target_F_mm``: the TRE point (default :func:`default_target`).
    ``quality``: ``"default"`` or ``"fast"`` renderer sampling (see module docstring).
    ``sections``: which tubes count (:func:`counted_tubes`).
    Raises ``ValueError`` when the slices carry no information on some pose
    parameter (e.g. fewer than three tubes in view).
    """
    protocol = protocol or Protocol()
    if quality not in QUALITY:
        raise ValueError(f"quality is {quality!r}; allowed: {', '.join(QUALITY)}")
    target = tuple(float(v) for v in (target_F_mm if target_F_mm is not None else default_target(geom)))
    F = fisher_information(geom, depth_mm, tilt_deg, azimuth_deg, twist_deg, protocol, quality, sections)
    if not np.all(np.isfinite(F)) or np.linalg.cond(F) > 1e14:
        raise ValueError(f"the slices at depth {depth_mm:g} mm, tilt {tilt_deg:g} deg do not determine the pose")
    C = np.linalg.inv(F)[:6, :6]
    C = 0.5 * (C + C.T)
    s = deg_mm_scale()
    cov = C * np.outer(s, s)
    T = slice_frame(depth_mm, tilt_deg, azimuth_deg, twist_deg)
    return PrecisionBound(float(depth_mm), float(tilt_deg), float(azimuth_deg), float(twist_deg), cov,
                          target_F_mm=target, protocol=protocol, fisher=F, **summarise(cov, T, target))


#: Columns of :func:`precision_map`'s table.
MAP_COLUMNS = ("depth_mm", "tilt_deg", "sd_normal_deg", "sd_twist_deg", "sd_depth_mm", "tre_mm",
               "worst_tre_mm", "n_azimuths")


@dataclass(frozen=True)
class PrecisionMap:
    """The bound over depth and tilt: each row is the mean over azimuths (RMS of the per-azimuth bounds) and the worst TRE.

    ``rows``: one dict per (depth, tilt) with :data:`MAP_COLUMNS`; ``NaN``
    where the slices do not determine the pose. Twist (an in-plane rotation of
    the image) only moves the pixel grid and is held at 0.
    """

    rows: tuple
    protocol: Protocol
    target_F_mm: tuple[float, float, float]
    azimuths_deg: tuple[float, ...]

    def column(self, name: str) -> np.ndarray:
        return np.array([r[name] for r in self.rows], float)

    def to_dict(self) -> dict:
        return {"protocol": self.protocol.to_dict(), "target_F_mm": list(self.target_F_mm),
                "azimuths_deg": list(self.azimuths_deg),
                "aggregate": "RMS over azimuths (worst_tre_mm: maximum over azimuths); twist 0",
                "rows": [dict(r) for r in self.rows]}


def precision_map(geom: FiducialGeometry, protocol: Protocol | None = None, depths_mm=None, tilts_deg=(0.0, 15.0, 30.0),
                  target_F_mm=None, *, n_azimuths: int = 4, quality: str = "fast") -> PrecisionMap:
    """The CRLB over ``depths_mm`` x ``tilts_deg`` (default depths: 10 % to 90 % of the body in 9 steps).

    Each cell aggregates ``n_azimuths`` azimuths evenly spread over 360 deg:
    RMS of the SDs (the mean precision over azimuth) and the worst TRE.
    """
    protocol = protocol or Protocol()
    L = float(geom.body.length)
    depths = np.linspace(0.1 * L, 0.9 * L, 9) if depths_mm is None else np.asarray(depths_mm, float)
    target = tuple(float(v) for v in (target_F_mm if target_F_mm is not None else default_target(geom)))
    azimuths = tuple(float(a) for a in np.arange(int(n_azimuths)) * 360.0 / int(n_azimuths))
    rows = []
    keys = ("sd_normal_deg", "sd_twist_deg", "sd_depth_mm", "tre_mm")
    for d in depths:
        for t in tilts_deg:
            vals = {k: [] for k in keys}
            for a in azimuths:
                try:
                    b = pose_crlb(geom, float(d), float(t), a, 0.0, protocol, target, quality=quality)
                except ValueError:
                    continue
                for k in keys:
                    vals[k].append(getattr(b, k))
            row = {"depth_mm": float(d), "tilt_deg": float(t), "n_azimuths": len(vals["tre_mm"])}
            for k in keys:
                row[k] = float(np.sqrt(np.mean(np.square(vals[k])))) if vals[k] else float("nan")
            row["worst_tre_mm"] = float(max(vals["tre_mm"])) if vals["tre_mm"] else float("nan")
            rows.append(row)
    return PrecisionMap(tuple(rows), protocol, target, azimuths)
