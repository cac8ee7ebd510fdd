"""Reformat a volume into oblique slices at known poses, and the paper's Table II study.

:func:`reslice` samples a volume (trilinear, ``sitk.Resample``) on the pixel
grid of an oblique plane and returns a :class:`~chic_register.model.slices.Slice`
in the volume's LPS frame, so the solver sees it like any acquired slice.

:func:`reslice_study` repeats the paper's reformatted-MRI test (Table II): a
volume whose fiducial pose ``T_scanner_from_fiducial`` is known (or taken as
the reference) is resliced at a series of depths with a fixed tilt relative
to the fiducial axis (15 degrees in the paper), each slice is registered on
its own, and the errors are summarised per axis as RMS and standard
deviation.

Error of one slice, all in the fiducial frame F: the true slice frame S has
its origin on the fiducial axis at the true depth. Mapping S into F with the
*estimated* registration gives ``T_F_from_S_est = inv(T_est) @
T_scanner_from_S``; ``x, y, z`` errors are its origin minus ``(0, 0,
depth)`` (where the estimate puts the true axis crossing), ``tilt`` and
``twist`` errors are :func:`~chic_register.model.pose.slice_angles` of it minus
the true angles.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from chic_register.errors import NoLock
from chic_register.model.pose import invert, slice_angles, slice_frame, wrap_deg
from chic_register.model.slices import Slice
from chic_register.pipeline.register import register as register_slices

AXES = ("x_mm", "y_mm", "z_mm", "tilt_deg", "twist_deg")


def _as_sitk(volume) -> sitk.Image:
    if isinstance(volume, sitk.Image):
        return volume
    return sitk.Cast(volume.to_sitk(), sitk.sitkFloat32)


def reslice(
    volume,
    T_scanner_from_slice,
    shape=(256, 256),
    pixel_spacing_mm=(0.5, 0.5),
    *,
    center_px=None,
    slice_thickness_mm: float = 0.0,
    thickness_samples: int | None = None,
    source: str = "<resliced>",
) -> Slice:
    """The oblique slice of ``volume`` whose frame S is ``T_scanner_from_slice`` (4x4).

    ``volume``: a :class:`~chic_register.io.volumes.Volume` or its SimpleITK image.
    Pixel (row i, col j) is centred at S coordinates ``((j - cc) *
    col_spacing, (i - rc) * row_spacing, 0)`` with ``(rc, cc) = center_px``
    (default: the image centre), the convention of
    :func:`chic_register.imaging.render.render_slice`. Samples are trilinear;
    outside the volume they are 0. With ``slice_thickness_mm > 0`` each
    pixel averages ``thickness_samples`` planes across the thickness (a slab,
    default one plane per 0.5 voxel). Returns a Slice with pixels of shape
    ``shape`` (rows, cols).
    """
    img = _as_sitk(volume)
    rows, cols = (int(n) for n in shape)
    rs, cs = (float(s) for s in pixel_spacing_mm)
    if rows < 1 or cols < 1 or not (rs > 0 and cs > 0):
        raise ValueError(f"bad grid: shape {tuple(shape)}, pixel_spacing_mm {tuple(pixel_spacing_mm)}")
    rc, cc = ((rows - 1) / 2.0, (cols - 1) / 2.0) if center_px is None else (float(c) for c in center_px)
    T = np.asarray(T_scanner_from_slice, dtype=float)
    x, y = T[:3, 0], T[:3, 1]
    z = np.cross(x, y)
    origin = T[:3, 3] - cc * cs * x - rc * rs * y
    thick = float(slice_thickness_mm)
    if thick > 0:
        if thickness_samples is None:
            thickness_samples = max(1, int(math.ceil(2.0 * thick / min(img.GetSpacing()))))
        n = int(thickness_samples)
    else:
        n = 1
    dz = thick / n if n > 1 else 1.0
    start = origin - 0.5 * (n - 1) * dz * z if n > 1 else origin
    direction = np.stack([x, y, z], axis=1)
    out = sitk.Resample(
        img,
        [cols, rows, n],
        sitk.Transform(),
        sitk.sitkLinear,
        tuple(start),
        (cs, rs, dz),
        tuple(direction.ravel()),
        0.0,
        sitk.sitkFloat32,
    )
    pixels = sitk.GetArrayFromImage(out).astype(float).mean(axis=0)
    return Slice(pixels, (rs, cs), origin, x.copy(), y.copy(), thick, source)


# --------------------------------------------------------------------------- the Table II study


@dataclass(frozen=True)
class ResliceResult:
    """One reformatted slice: its true angles and the errors of its registration (NaN when no lock)."""

    depth_mm: float
    tilt_deg: float
    azimuth_deg: float
    twist_deg: float
    status: str
    errors: dict = field(default_factory=dict)  # AXES -> error (mm or deg)
    reason: str = ""
    solve_ms: float = float("nan")

    def to_dict(self) -> dict:
        return {
            "depth_mm": self.depth_mm,
            "tilt_deg": self.tilt_deg,
            "azimuth_deg": self.azimuth_deg,
            "twist_deg": self.twist_deg,
            "status": self.status,
            "errors": {k: float(v) for k, v in self.errors.items()},
            **({"reason": self.reason} if self.reason else {}),
            "solve_ms": self.solve_ms,
        }


@dataclass(frozen=True)
class ResliceStudy:
    """All slices of a study and the per-axis summary (RMS and SD over the slices that locked)."""

    results: tuple[ResliceResult, ...]
    settings: dict

    @property
    def locked(self) -> tuple[ResliceResult, ...]:
        return tuple(r for r in self.results if r.status == "ok")

    def errors(self) -> np.ndarray:
        """Errors of the locked slices; shape (N, 5) in AXES order."""
        return np.array([[r.errors[a] for a in AXES] for r in self.locked]).reshape(-1, len(AXES))

    def summary(self) -> dict:
        """``{axis: {"rms", "sd", "mean", "max_abs"}}`` over the locked slices (SD with ddof=1)."""
        e = self.errors()
        out = {}
        for i, a in enumerate(AXES):
            col = e[:, i]
            n = col.size
            out[a] = {
                "rms": float(np.sqrt(np.mean(col**2))) if n else float("nan"),
                "sd": float(np.std(col, ddof=1)) if n > 1 else float("nan"),
                "mean": float(np.mean(col)) if n else float("nan"),
                "max_abs": float(np.max(np.abs(col))) if n else float("nan"),
            }
        return out

    def to_dict(self) -> dict:
        return {
            "settings": dict(self.settings),
            "n_slices": len(self.results),
            "n_locked": len(self.locked),
            "summary": self.summary(),
            "slices": [r.to_dict() for r in self.results],
        }

    def table(self) -> str:
        """The summary laid out like the paper's Table II."""
        s = self.summary()
        units = ("mm", "mm", "mm", "°", "°")
        head = f"{'':20s}" + "".join(f"{h:>10s}" for h in ("X", "Y", "Z", "Tilt", "Twist"))

        def row(label, key):
            cells = "".join(f"{s[a][key]:>8.3f}{u:<2s}" for a, u in zip(AXES, units))
            return f"{label:20s}{cells}"

        lines = [head, row("RMS Error", "rms"), row("Standard Deviation", "sd")]
        lines.append(f"{len(self.locked)} of {len(self.results)} slices locked")
        return "\n".join(lines)


def slice_errors(T_scanner_from_fiducial_est, T_scanner_from_slice, true_angles) -> dict:
    """Errors of one registration for a slice of known pose (see the module docstring); AXES -> value."""
    T_F_from_S_est = invert(np.asarray(T_scanner_from_fiducial_est, dtype=float)) @ T_scanner_from_slice
    est = slice_angles(T_F_from_S_est)
    p = T_F_from_S_est[:3, 3]
    return {
        "x_mm": float(p[0]),
        "y_mm": float(p[1]),
        "z_mm": float(p[2] - true_angles.depth_mm),
        "tilt_deg": float(est.tilt_deg - true_angles.tilt_deg),
        "twist_deg": float(wrap_deg(est.twist_deg - true_angles.twist_deg)),
    }


def default_depths(geom, tilt_deg: float = 15.0, step_mm: float = 2.0, margin_mm: float | None = None) -> np.ndarray:
    """Depths (mm) across the body where a slice at ``tilt_deg`` stays inside the tubes' z range.

    The margin keeps the tilted plane, which spans ``± r tan(tilt)`` in z at
    the tube radius ``r``, inside the body with 2 mm to spare.
    """
    r = 0.5 * geom.body.outer_diameter
    if margin_mm is None:
        margin_mm = r * math.tan(math.radians(tilt_deg)) + 2.0
    lo, hi = margin_mm, geom.body.length - margin_mm
    if hi < lo:
        return np.array([0.5 * geom.body.length])
    n = int(math.floor((hi - lo) / step_mm)) + 1
    start = 0.5 * (lo + hi) - 0.5 * (n - 1) * step_mm
    return start + step_mm * np.arange(n)


def reslice_study(
    volume,
    geom,
    T_scanner_from_fiducial_true,
    *,
    depths_mm=None,
    tilt_deg: float = 15.0,
    azimuth_deg: float = 0.0,
    twist_deg: float = 0.0,
    shape=(256, 256),
    pixel_spacing_mm=(0.5, 0.5),
    slice_thickness_mm: float = 0.0,
    register=None,
    **register_options,
) -> ResliceStudy:
    """The paper's Table II protocol on ``volume`` (see the module docstring).

    Each depth in ``depths_mm`` (default :func:`default_depths`) gives one
    slice with S = ``T_scanner_from_fiducial_true @ slice_frame(depth,
    tilt, azimuth, twist)``, resliced by :func:`reslice` and registered on
    its own by ``register`` (default :func:`chic_register.pipeline.register.register`,
    called as ``register([slice], geom, **register_options)``). A slice
    without lock counts in the table's footer, not in its numbers.
    """
    if register is None:
        register = register_slices
    img = _as_sitk(volume)
    T_true = np.asarray(T_scanner_from_fiducial_true, dtype=float)
    depths = default_depths(geom, tilt_deg) if depths_mm is None else np.atleast_1d(np.asarray(depths_mm, float))
    results = []
    for d in depths:
        T_F_from_S = slice_frame(float(d), tilt_deg, azimuth_deg, twist_deg)
        T_scanner_from_S = T_true @ T_F_from_S
        truth = slice_angles(T_F_from_S)
        sl = reslice(img, T_scanner_from_S, shape, pixel_spacing_mm,
                     slice_thickness_mm=slice_thickness_mm, source=f"reslice depth {float(d):.2f} mm")
        t0 = time.perf_counter()
        try:
            reg = register([sl], geom, **register_options)
        except NoLock as exc:
            ms = 1000.0 * (time.perf_counter() - t0)
            results.append(ResliceResult(float(d), truth.tilt_deg, truth.azimuth_deg, truth.twist_deg,
                                         "no_lock", {a: float("nan") for a in AXES}, exc.reason, ms))
            continue
        ms = 1000.0 * (time.perf_counter() - t0)
        errs = slice_errors(reg.T_scanner_from_fiducial, T_scanner_from_S, truth)
        results.append(ResliceResult(float(d), truth.tilt_deg, truth.azimuth_deg, truth.twist_deg, "ok", errs, "", ms))
    settings = {
        "tilt_deg": float(tilt_deg),
        "azimuth_deg": float(azimuth_deg),
        "twist_deg": float(twist_deg),
        "depths_mm": [float(d) for d in depths],
        "shape": [int(s) for s in shape],
        "pixel_spacing_mm": [float(s) for s in pixel_spacing_mm],
        "slice_thickness_mm": float(slice_thickness_mm),
        "volume_spacing_mm": list(img.GetSpacing()),
        "volume_size_ijk": list(img.GetSize()),
    }
    return ResliceStudy(tuple(results), settings)
