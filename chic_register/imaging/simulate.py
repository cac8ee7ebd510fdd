"""Synthetic MRI slices of a fiducial at a known pose, with partial volume and noise.

A slice's image is the fluid fraction of each pixel, rendered by
:mod:`chic_register.imaging.render` (:func:`render_tubes` and :func:`render_slice`
are importable from here too), widened to a blob-width factor if asked
(:mod:`chic_register.imaging.blob_width`), with bright distractors, a tool in the
bore, uniform or Rician noise; placed in the scanner as a DICOM-like
:class:`~chic_register.model.slices.Slice`, with its truth (the pose and the
analytic crossings in pixels) written beside the image file.

Pixel (row i, col j) has its centre at slice-frame coordinates
``x = (j - cc) * col_spacing``, ``y = (i - rc) * row_spacing`` with
``(rc, cc) = center_px``; the slice frame S is given by ``T_F_from_S``
(see :func:`chic_register.model.pose.slice_frame`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from chic_register.imaging.blob_width import render_tubes_widened
from chic_register.imaging.ct import CT_PIXEL_MM, CT_SHAPE, CT_THICKNESS_MM, CTScene, hounsfield_slice
from chic_register.imaging.render import check_grid, render_tubes, sample_offsets
from chic_register.io.images import PLAIN_SUFFIXES, write_plain_image
from chic_register.io.volumes import Volume, plane_frame
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import (
    SliceAngles,
    apply,
    invert,
    rigid,
    slice_angles,
    slice_frame,
)
from chic_register.model.slices import Slice
from chic_register.model.tubes import LineTube
from chic_register.util.atomic import write_json

NOISE_KINDS = ("none", "uniform", "rician")


def crossings_px(geom: FiducialGeometry, T_F_from_S: np.ndarray, pixel_spacing_mm=(0.5, 0.5), center_px=(0.0, 0.0)):
    """Analytic crossings of every tube centreline with the plane z = 0 of S, in pixels.

    Returns ``{tube_id: (K, 2) array of (row, col)}`` (K = 0 when a tube misses
    the plane), computed with the geometry's own ``intersect_plane``.
    """
    T = np.asarray(T_F_from_S, dtype=float)
    T_S_from_F = invert(T)
    rs, cs = (float(v) for v in pixel_spacing_mm)
    out = {}
    for tid, pts in geom.intersect_plane(T[:3, 3], T[:3, 2]).items():
        if len(pts) == 0:
            out[tid] = np.empty((0, 2))
            continue
        s = apply(T_S_from_F, pts)
        out[tid] = np.stack([s[:, 1] / rs + center_px[0], s[:, 0] / cs + center_px[1]], axis=1)
    return out


# --------------------------------------------------------------------------- noise


def add_uniform_noise(image: np.ndarray, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """The paper's white noise: ``image + U(-amplitude, amplitude)``, clipped at 0 (a new array)."""
    if not (amplitude >= 0 and math.isfinite(amplitude)):
        raise ValueError(f"noise amplitude must be >= 0, got {amplitude}")
    img = np.asarray(image, dtype=float)
    return np.clip(img + rng.uniform(-amplitude, amplitude, img.shape), 0.0, None)


def add_rician_noise(image: np.ndarray, snr: float, rng: np.random.Generator, signal: float = 1.0) -> np.ndarray:
    """MRI magnitude noise: ``|signal * image + N(0, s) + i N(0, s)|`` with ``s = signal / snr``.

    Fluid (image 1) then has SNR ``snr``; the background follows a Rayleigh
    distribution of scale ``s``.
    """
    if not (snr > 0 and math.isfinite(snr)):
        raise ValueError(f"snr must be > 0, got {snr}")
    img = np.asarray(image, dtype=float)
    s = signal / snr
    return np.hypot(signal * img + rng.normal(0.0, s, img.shape), rng.normal(0.0, s, img.shape))


# --------------------------------------------------------------------------- simulated slices


def tool_truth(T_fiducial_from_tool, T_scanner_from_fiducial) -> dict:
    """The truth of a geometry's tool frame at a known pose, with the keys ``solve --json`` uses.

    ``T_fiducial_from_tool`` and ``T_scanner_from_tool`` (4x4), the tip in F
    (``tool_tip_F_mm``) and in the scanner (``tool_tip_mm``): the tool frame's
    origin is the tip (docs/interfaces.md section 2).
    """
    T_F_tool = np.asarray(T_fiducial_from_tool, dtype=float)
    T_scanner_tool = np.asarray(T_scanner_from_fiducial, dtype=float) @ T_F_tool
    return {
        "T_fiducial_from_tool": T_F_tool.tolist(),
        "T_scanner_from_tool": T_scanner_tool.tolist(),
        "tool_tip_F_mm": [float(v) for v in T_F_tool[:3, 3]],
        "tool_tip_mm": [float(v) for v in T_scanner_tool[:3, 3]],
    }



@dataclass(frozen=True)
class SliceTruth:
    """The known pose of a simulated slice.

    ``T_scanner_from_fiducial`` (4x4) maps F to the slice's scanner frame;
    ``centres_px`` holds ``(row, col)`` of each visible tube's crossing (the
    one nearest the axis crossing when a helix crosses more than once);
    ``crossings_px`` every crossing inside the image; ``center_px`` is the
    pixel where the fiducial axis crosses the plane (S origin);
    ``T_fiducial_from_tool`` the geometry's tool frame, if it has one (the
    truth file then holds the tool tip, :func:`tool_truth`).
    """

    angles: SliceAngles
    T_scanner_from_fiducial: np.ndarray
    centres_px: dict
    T_F_from_S: np.ndarray
    center_px: tuple[float, float]
    crossings_px: dict = field(default_factory=dict)
    missing_tubes: tuple[str, ...] = ()
    pixel_spacing_mm: tuple[float, float] = (0.5, 0.5)
    slice_thickness_mm: float = 0.0
    shape: tuple[int, int] = (256, 256)
    settings: dict = field(default_factory=dict)
    T_fiducial_from_tool: np.ndarray | None = None

    def to_dict(self) -> dict:
        """JSON-ready dictionary (angles in degrees, lengths in mm, pixels as (row, col))."""
        a = self.angles
        tool = {} if self.T_fiducial_from_tool is None else tool_truth(self.T_fiducial_from_tool,
                                                                       self.T_scanner_from_fiducial)
        return {
            "depth_mm": float(a.depth_mm),
            "tilt_deg": float(a.tilt_deg),
            "azimuth_deg": float(a.azimuth_deg),
            "twist_deg": float(a.twist_deg),
            "T_scanner_from_fiducial": np.asarray(self.T_scanner_from_fiducial).tolist(),
            "T_F_from_S": np.asarray(self.T_F_from_S).tolist(),
            "centres_px": {k: [float(v[0]), float(v[1])] for k, v in self.centres_px.items()},
            "crossings_px": {k: np.asarray(v).tolist() for k, v in self.crossings_px.items()},
            "axis_crossing_px": [float(self.center_px[0]), float(self.center_px[1])],
            "missing_tubes": list(self.missing_tubes),
            "shape": [int(self.shape[0]), int(self.shape[1])],
            "pixel_spacing_mm": [float(v) for v in self.pixel_spacing_mm],
            "slice_thickness_mm": float(self.slice_thickness_mm),
            "settings": dict(self.settings),
            **tool,
        }


@dataclass(frozen=True)
class SimulatedSlice:
    """A synthetic :class:`~chic_register.model.slices.Slice` and its truth."""

    slice: Slice
    truth: SliceTruth


def _scanner_placement(shape, spacing, T_scanner_from_image, image_position, image_orientation):
    """(origin_mm, col_dir, row_dir) of the slice in the scanner; default: axial, centre pixel at 0."""
    if T_scanner_from_image is not None:
        if image_position is not None or image_orientation is not None:
            raise ValueError("give either T_scanner_from_image or image_position/image_orientation, not both")
        T = np.asarray(T_scanner_from_image, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"T_scanner_from_image must be 4x4, got shape {T.shape}")
        col_dir, row_dir, origin = T[:3, 0], T[:3, 1], T[:3, 3]
    else:
        if image_orientation is None:
            col_dir, row_dir = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
        else:
            o = np.asarray(image_orientation, dtype=float).reshape(-1)
            if o.size != 6:
                raise ValueError(f"image_orientation needs 6 numbers (col_dir, row_dir), got {o.size}")
            col_dir, row_dir = o[:3], o[3:]
        if image_position is None:
            rows, cols = shape
            origin = -((cols - 1) / 2.0 * spacing[1]) * col_dir - ((rows - 1) / 2.0 * spacing[0]) * row_dir
        else:
            origin = np.asarray(image_position, dtype=float).reshape(3)
    ok = (
        abs(np.linalg.norm(col_dir) - 1) < 1e-6
        and abs(np.linalg.norm(row_dir) - 1) < 1e-6
        and abs(float(col_dir @ row_dir)) < 1e-6
        and np.all(np.isfinite(origin))
    )
    if not ok:
        raise ValueError("image orientation must be two orthonormal vectors (col_dir, row_dir)")
    return np.array(origin, dtype=float), np.array(col_dir, dtype=float), np.array(row_dir, dtype=float)


def _render_distractors(n, geom, T_F_from_S, grid_shape, spacing, center, rng, supersample):
    """``n`` anatomy-like bright ellipses in the image, all outside the fiducial body; shape (rows, cols)."""
    rows, cols = grid_shape
    rs, cs = spacing
    out = np.zeros(grid_shape)
    if n <= 0:
        return out
    R, tF = T_F_from_S[:3, :3], T_F_from_S[:3, 3]
    r_out = 0.5 * geom.body.outer_diameter
    length = geom.body.length
    sub = sample_offsets(supersample)
    placed = 0
    for _ in range(200 * n):
        if placed == n:
            break
        a = rng.uniform(1.0, 4.0)
        b = rng.uniform(1.0, 4.0)
        phi = rng.uniform(0, math.pi)
        i_c = rng.uniform(0, rows - 1)
        j_c = rng.uniform(0, cols - 1)
        x_c, y_c = (j_c - center[1]) * cs, (i_c - center[0]) * rs
        pF = R @ np.array([x_c, y_c, 0.0]) + tF
        clear = max(a, b) + 1.0
        if math.hypot(pF[0], pF[1]) < r_out + clear and -clear < pF[2] < length + clear:
            continue
        h = max(a, b) + 2 * max(rs, cs)
        i0, i1 = max(0, int((y_c - h) / rs + center[0])), min(rows - 1, int((y_c + h) / rs + center[0]) + 1)
        j0, j1 = max(0, int((x_c - h) / cs + center[1])), min(cols - 1, int((x_c + h) / cs + center[1]) + 1)
        ys = ((np.arange(i0, i1 + 1)[:, None] + sub) - center[0]) * rs - y_c
        xs = ((np.arange(j0, j1 + 1)[:, None] + sub) - center[1]) * cs - x_c
        X = xs[None, :, None, :]
        Y = ys[:, None, :, None]
        cp, sp = math.cos(phi), math.sin(phi)
        inside = ((X * cp + Y * sp) / a) ** 2 + ((-X * sp + Y * cp) / b) ** 2 <= 1.0
        frac = inside.mean(axis=(2, 3)) * rng.uniform(0.6, 1.0)
        region = out[i0 : i1 + 1, j0 : j1 + 1]
        np.maximum(region, frac, out=region)
        placed += 1
    return out


def simulate_slice(
    geom: FiducialGeometry,
    depth_mm: float,
    tilt_deg: float,
    azimuth_deg: float = 0.0,
    twist_deg: float = 0.0,
    *,
    shape=(256, 256),
    pixel_spacing_mm=(0.5, 0.5),
    slice_thickness_mm: float = 2.0,
    center_offset_mm=(0.0, 0.0),
    noise: str = "none",
    noise_level: float = 0.1,
    snr: float = 20.0,
    distractors: int = 0,
    bore_signal: float = 0.0,
    missing_tubes=(),
    T_scanner_from_image=None,
    image_position=None,
    image_orientation=None,
    T_scanner_from_fiducial=None,
    rng=None,
    supersample: int = 4,
    thickness_samples: int = 5,
    blob_width: float = 1.0,
    modality: str = "MR",
    ct: CTScene | None = None,
) -> SimulatedSlice:
    """A synthetic slice of ``geom`` at a known pose, with its truth.

    The slice cuts F as :func:`~chic_register.model.pose.slice_frame` (depth, tilt,
    azimuth, twist) says; the fiducial axis crosses the image
    ``center_offset_mm`` (x along columns, y along rows) from the image centre.
    ``noise``: ``"none"``, ``"uniform"`` (+ U(-noise_level, noise_level)) or
    ``"rician"`` (magnitude noise at ``snr``). ``distractors`` bright blobs are
    placed outside the body; ``bore_signal > 0`` puts a tool of that
    brightness along the axis in the bore; ``missing_tubes`` ids are left
    unfilled. The slice sits in the scanner by ``T_scanner_from_image``, or by
    DICOM-like ``image_position`` (scanner position of pixel (0, 0)) and
    ``image_orientation`` (col_dir, row_dir); default: an axial image whose
    centre pixel is at the scanner origin. Or give ``T_scanner_from_fiducial``
    (4x4): the fiducial's pose in the scanner, from which the slice is placed
    (slices of one series share it). ``blob_width`` draws every tube's blob
    that many times its nominal width, as real images do (0.7-2.5x; see
    :class:`BlobWidth`). ``modality="CT"``: the slice in Hounsfield units, its rods, plates, distractors and
    Gaussian noise as ``ct`` (a :class:`~chic_register.imaging.ct.CTScene`, default its defaults) says; the
    fluid share (with distractors and tool) is filled at the scene's ``rod_hu``; ``noise`` must be "none".
    ``truth.T_scanner_from_fiducial = slice.T_scanner_from_image() @ T_image_from_S @ invert(T_F_from_S)``.
    """
    if noise not in NOISE_KINDS:
        raise ValueError(f"noise is {noise!r}; allowed: {', '.join(NOISE_KINDS)}")
    if modality not in ("MR", "CT"):
        raise ValueError(f"modality is {modality!r}; allowed: MR, CT")
    if modality == "CT" and noise != "none":
        raise ValueError("a CT slice's noise is the scene's Gaussian noise_hu; give noise='none'")
    missing = tuple(str(m) for m in missing_tubes)
    unknown = [m for m in missing if m not in geom.ids]
    if unknown:
        raise ValueError(f"missing_tubes: unknown tube id(s) {', '.join(unknown)}; known: {', '.join(geom.ids)}")
    if int(distractors) < 0:
        raise ValueError(f"distractors must be >= 0, got {distractors}")
    if not (bore_signal >= 0 and math.isfinite(bore_signal)):
        raise ValueError(f"bore_signal must be >= 0, got {bore_signal}")
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    (rows, cols), spacing, _ = check_grid(shape, pixel_spacing_mm, None, supersample, thickness_samples, slice_thickness_mm)
    rs, cs = spacing
    dx, dy = (float(v) for v in center_offset_mm)
    center = ((rows - 1) / 2.0 + dy / rs, (cols - 1) / 2.0 + dx / cs)
    T_F_from_S = slice_frame(depth_mm, tilt_deg, azimuth_deg, twist_deg)

    tubes = [t for t in geom.tubes if t.id not in missing]
    image = render_tubes_widened(tubes, T_F_from_S, (rows, cols), spacing, slice_thickness_mm, center, supersample,
                                 thickness_samples, blob_width)
    if bore_signal > 0:
        L = geom.body.length
        tool = LineTube("tool", "other", (0.0, 0.0, -L), (0.0, 0.0, 2.0 * L), 0.4 * geom.body.inner_diameter)
        tool_img = render_tubes([tool], T_F_from_S, (rows, cols), spacing, slice_thickness_mm, center, supersample, thickness_samples)
        image = np.maximum(image, bore_signal * tool_img)
    if distractors:
        blobs = _render_distractors(int(distractors), geom, T_F_from_S, (rows, cols), spacing, center, rng, supersample)
        image = np.maximum(image, blobs)
    if modality == "CT":
        ct = ct or CTScene()
        image = hounsfield_slice(geom, np.clip(image, 0.0, 1.0), T_F_from_S, spacing, center,
                                 float(slice_thickness_mm), ct, rng)
    elif noise == "uniform":
        image = add_uniform_noise(image, noise_level, rng)
    elif noise == "rician":
        image = add_rician_noise(image, snr, rng)

    T_image_from_S = rigid(np.eye(3), (center[1] * cs, center[0] * rs, 0.0))
    if T_scanner_from_fiducial is not None:
        if T_scanner_from_image is not None or image_position is not None or image_orientation is not None:
            raise ValueError("give the fiducial's pose or the image placement, not both")
        T_sf = np.asarray(T_scanner_from_fiducial, dtype=float)
        R = T_sf[:3, :3] if T_sf.shape == (4, 4) else np.zeros((3, 3))
        if not (np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0 and np.allclose(T_sf[3], (0, 0, 0, 1))):
            raise ValueError("T_scanner_from_fiducial must be a 4x4 rigid transform (rotation + translation)")
        T_scanner_from_image = T_sf @ T_F_from_S @ invert(T_image_from_S)
    origin, col_dir, row_dir = _scanner_placement(
        (rows, cols), spacing, T_scanner_from_image, image_position, image_orientation
    )
    sl = Slice(image, (rs, cs), origin, col_dir, row_dir, float(slice_thickness_mm), "<simulated>",
               modality="CT" if modality == "CT" else "auto")
    T_scanner_from_fiducial = sl.T_scanner_from_image() @ T_image_from_S @ invert(T_F_from_S)

    all_px = crossings_px(geom, T_F_from_S, spacing, center)
    crossings, centres = {}, {}
    for tid, px in all_px.items():
        if tid in missing:
            continue
        inside = px[(px[:, 0] >= -0.5) & (px[:, 0] <= rows - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= cols - 0.5)]
        if len(inside) == 0:
            continue
        crossings[tid] = inside
        k = int(np.argmin(np.hypot(inside[:, 0] - center[0], inside[:, 1] - center[1])))
        centres[tid] = (float(inside[k, 0]), float(inside[k, 1]))
    settings = {
        "noise": noise,
        "noise_level": float(noise_level) if noise == "uniform" else None,
        "snr": float(snr) if noise == "rician" else None,
        "distractors": int(distractors),
        "bore_signal": float(bore_signal),
        "center_offset_mm": [dx, dy],
        "geometry": geom.name,
        "blob_width": float(blob_width),
        "modality": modality,
        **({"ct": ct.to_dict()} if modality == "CT" else {}),
    }
    truth = SliceTruth(
        angles=slice_angles(T_F_from_S),
        T_scanner_from_fiducial=T_scanner_from_fiducial,
        centres_px=centres,
        T_F_from_S=T_F_from_S,
        center_px=center,
        crossings_px=crossings,
        missing_tubes=missing,
        pixel_spacing_mm=(rs, cs),
        slice_thickness_mm=float(slice_thickness_mm),
        shape=(rows, cols),
        settings=settings,
        T_fiducial_from_tool=None if geom.tool is None else geom.tool.T_fiducial_from_tool,
    )
    return SimulatedSlice(sl, truth)


def simulate_ct_slice(geom: FiducialGeometry, depth_mm: float, tilt_deg: float, azimuth_deg: float = 0.0,
                      twist_deg: float = 0.0, *, scene: CTScene | None = None, shape=CT_SHAPE,
                      pixel_spacing_mm=(CT_PIXEL_MM, CT_PIXEL_MM), slice_thickness_mm: float = CT_THICKNESS_MM,
                      **kwargs) -> SimulatedSlice:
    """A synthetic CT slice (Hounsfield units) on a CT's usual grid: :func:`simulate_slice` with
    ``modality="CT"``; ``kwargs`` go to it."""
    return simulate_slice(geom, depth_mm, tilt_deg, azimuth_deg, twist_deg, shape=shape,
                          pixel_spacing_mm=pixel_spacing_mm, slice_thickness_mm=slice_thickness_mm,
                          modality="CT", ct=scene or CTScene(), **kwargs)


# --------------------------------------------------------------------------- files

DICOM_SUFFIXES = (".dcm", ".dicom")


def truth_path(image_path) -> Path:
    """Where the truth of a simulated image is written: ``<image>.truth.json``."""
    p = Path(image_path)
    return p.with_name(p.name + ".truth.json")


def write_simulated(sim: SimulatedSlice, path, extra: dict | None = None):
    """Write a simulated slice (DICOM, NPY, PNG or TIFF by suffix) and its truth JSON beside it.

    Plain images carry no placement, so their truth is in the image frame
    (docs/interfaces.md section 3): ``sim.slice`` must then sit at the scanner origin
    with identity orientation (``image_position=(0, 0, 0)``, the default
    orientation). Both files are written atomically. Returns
    ``(image_path, truth_path)``.
    """
    from chic_register.io.dicom import write_dicom  # deferred: loads pydicom only when used (one-shot start-up)

    p = Path(path)
    suffix = p.suffix.lower()
    info = {"image": p.name, "frame": "LPS" if suffix in DICOM_SUFFIXES else "image"}
    if suffix in DICOM_SUFFIXES:
        write_dicom(sim.slice, p, truth=sim.truth)
        info["format"] = "dicom"
    elif suffix in PLAIN_SUFFIXES:
        sl = sim.slice
        if not (np.allclose(sl.T_scanner_from_image(), np.eye(4))):
            raise ValueError(f"{p}: a plain image has no scanner placement; simulate it in the image frame")
        info.update(write_plain_image(sl.pixels, p))
    else:
        allowed = ", ".join(DICOM_SUFFIXES + PLAIN_SUFFIXES)
        raise ValueError(f"{p}: unsupported output suffix {p.suffix!r}; allowed: {allowed}")
    doc = {**sim.truth.to_dict(), "file": info, **(extra or {})}
    return p, write_json(truth_path(p), doc)


@dataclass(frozen=True)
class SimulatedVolume:
    """A synthetic volume and the pose of the fiducial in it.

    ``T_scanner_from_fiducial`` (4x4): F (mm) -> the volume's LPS frame (mm).
    """

    volume: Volume
    T_scanner_from_fiducial: np.ndarray
    settings: dict = field(default_factory=dict)

    def truth_dict(self) -> dict:
        """JSON-ready truth: the pose plus the volume grid and the simulation settings."""
        v = self.volume
        return {
            "T_scanner_from_fiducial": np.asarray(self.T_scanner_from_fiducial).tolist(),
            "size_ijk": list(v.size_ijk),
            "spacing_mm": list(v.spacing_mm),
            "origin_mm": v.origin_mm.tolist(),
            "direction": v.direction.tolist(),
            "settings": dict(self.settings),
        }


def simulate_volume(
    geom,
    T_scanner_from_fiducial,
    shape_vox=(128, 128, 60),
    spacing_mm=(0.5, 0.5, 1.0),
    *,
    origin_mm=None,
    direction=None,
    signal: float = 1000.0,
    noise: str = "rician",
    noise_level: float = 0.05,
    snr: float = 20.0,
    rng=None,
    supersample: int = 3,
    thickness_samples: int = 3,
    blob_width: float = 1.0,
) -> SimulatedVolume:
    """A synthetic MRI volume of ``geom`` at a known pose.

    ``shape_vox``: (NX, NY, NZ) voxels along i, j, k; ``spacing_mm``: (si, sj, sk).
    Each voxel holds ``signal`` times its fluid fraction (partial volume over
    the voxel), rendered k-plane by k-plane with
    :func:`chic_register.imaging.render.render_slice` (plane thickness = sk), then
    noise as in :mod:`chic_register.imaging.simulate` (``"none"``, ``"uniform"``
    amplitude ``noise_level`` x signal, ``"rician"`` at ``snr``).
    Default placement: ``direction`` identity and the volume centre at the
    scanner origin. ``blob_width`` widens every blob in each k-plane as
    :func:`chic_register.imaging.blob_width.render_tubes_widened` does.
    """
    nx, ny, nz = (int(n) for n in shape_vox)
    if min(nx, ny, nz) < 1:
        raise ValueError(f"shape_vox must be three positive integers, got {tuple(shape_vox)}")
    si, sj, sk = (float(s) for s in spacing_mm)
    if not min(si, sj, sk) > 0:
        raise ValueError(f"spacing_mm must be three positive numbers, got {tuple(spacing_mm)}")
    if noise not in NOISE_KINDS:
        raise ValueError(f"noise is {noise!r}; allowed: {', '.join(NOISE_KINDS)}")
    D = np.eye(3) if direction is None else np.asarray(direction, dtype=float).reshape(3, 3)
    if not np.allclose(D.T @ D, np.eye(3), atol=1e-6):
        raise ValueError("direction must be an orthonormal 3x3 matrix (columns = LPS directions of i, j, k)")
    if origin_mm is None:
        origin_mm = -D @ (np.array([nx - 1, ny - 1, nz - 1]) * np.array([si, sj, sk]) / 2.0)
    T_sf = np.asarray(T_scanner_from_fiducial, dtype=float)
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)

    grid = Volume(np.zeros((1, 1, 1)), (si, sj, sk), origin_mm, D)
    T_fs = np.linalg.inv(T_sf)
    voxels = np.empty((nz, ny, nx))
    for k in range(nz):
        T_F_from_S = T_fs @ plane_frame(grid, k)
        voxels[k] = render_tubes_widened(
            geom.tubes, T_F_from_S, (ny, nx), (sj, si), sk, center_px=(0.0, 0.0),
            supersample=supersample, thickness_samples=thickness_samples, blob_width=blob_width,
        )
    if noise == "uniform":
        voxels = add_uniform_noise(voxels, noise_level, rng)
    elif noise == "rician":
        voxels = add_rician_noise(voxels, snr, rng)
    vol = Volume((signal * voxels).astype(np.float32), (si, sj, sk), origin_mm, D, "<simulated>")
    settings = {
        "geometry": geom.name,
        "signal": float(signal),
        "noise": noise,
        "noise_level": float(noise_level) if noise == "uniform" else None,
        "snr": float(snr) if noise == "rician" else None,
        "supersample": int(supersample),
        "thickness_samples": int(thickness_samples),
        "blob_width": float(blob_width),
    }
    return SimulatedVolume(vol, T_sf, settings)
