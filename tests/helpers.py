"""Helpers shared by tests in several folders (a test module never imports another).

The false-lock hunts' geometries and cases; simulated slices (square, Rician, blurred, near an end) and volumes (an
oblique placement); the z001 Z-frame and a Leksell-G-like N-localizer; pose errors and round-trip checks; one-line error checks and fuzzing settings;
the modules a fresh interpreter imports.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from scipy import ndimage as ndi
from scipy.spatial.transform import Rotation

from chic_design.families import geometry_of
from chic_design.spec import load_spec
from chic_register.errors import NoLock
from chic_register.imaging.render import render_tubes
from chic_register.imaging.simulate import add_rician_noise, simulate_slice, simulate_volume
from chic_register.model.body import Body, FrameCoordinates
from chic_register.model.geometry import FiducialGeometry, load_geometry
from chic_register.model.pose import apply, invert, rigid, rot_y, rot_z, slice_frame, wrap_deg
from chic_register.model.slices import Slice
from chic_register.model.tubes import LineTube
from chic_register.pipeline.register import register
from chic_register.studies.damage import make_case, pose_error, run_case

ROOT = Path(__file__).resolve().parents[1]

#: The false-lock hunts' designs (``benchmarks/hunt.py``'s default geometries).
HUNT_DESIGNS = {"neuro": ROOT / "designs" / "neuro.yaml", "needle-guide": ROOT / "designs" / "needle-guide.yaml"}


@functools.lru_cache(maxsize=1)
def hunt_geometries() -> dict:
    """The geometries the hunts solve with, by name: the exports, or the same built from ``designs/``."""
    out = {}
    for name, spec in HUNT_DESIGNS.items():
        export = ROOT / "exports" / name / "geometry.yaml"
        out[name] = load_geometry(export) if export.exists() else geometry_of(load_spec(spec))
    return out


def run_hunt_case(index: int, seed: int = 0) -> dict:
    """The hunt's judged outcome of one of its cases (``benchmarks/hunt.py --seed SEED --case INDEX``)."""
    geoms = hunt_geometries()
    return run_case(make_case(index, seed, geoms), geoms)


#: Options of tests that check the fit's accuracy against their own tolerances, also at poses whose single-slice
#: precision the solver cannot prove to 0.5 mm / 0.5 deg (a normal section's tilt): the precision refusal is lifted,
#: every other check of the pose (chic_register.verify.pixels) still applies.
ACCURACY_TEST = {"trust_tre_mm": math.inf, "trust_rot_deg": math.inf}


def check_round_trip(reg, sim, depth_tol=0.1, angle_tol=0.3, point_tol=0.3):
    """A registration of one simulated slice is ok and on its truth: angles, depth and fiducial points."""
    s = reg.slices[0]
    t = sim.truth.angles
    assert reg.status == "ok"
    assert s.depth_mm == pytest.approx(t.depth_mm, abs=depth_tol)
    # near a normal section only the helices see the tilt (the straight tubes barely move): looser
    assert s.tilt_deg == pytest.approx(t.tilt_deg, abs=angle_tol if t.tilt_deg > 10 else 2 * angle_tol)
    assert abs(wrap_deg(s.twist_deg - t.twist_deg)) < angle_tol
    if t.tilt_deg > 5:
        assert abs(wrap_deg(s.azimuth_deg - t.azimuth_deg)) < 2 * angle_tol
    # the whole transform: fiducial points land where the truth puts them
    pts = np.array([[0, 0, 0], [0, 0, 50], [12.5, 0, 25], [0, -12.5, 10]], float)
    d = apply(reg.T_scanner_from_fiducial, pts) - apply(sim.truth.T_scanner_from_fiducial, pts)
    assert np.abs(d).max() < point_tol


def simulate_square(geom, depth, tilt, az, tw, px=0.5, size=256, thick=2.0, noise="none", snr=20.0, seed=None,
                    **kw):
    """A square slice (``size`` pixels of ``px`` mm) at these angles, its image at the scanner's origin."""
    return simulate_slice(geom, depth, tilt, az, tw, shape=(size, size), pixel_spacing_mm=(px, px),
                          slice_thickness_mm=thick, noise=noise, snr=snr, image_position=(0.0, 0.0, 0.0),
                          rng=np.random.default_rng(seed), **kw)


def register_outcome(geom, sim, pixels=None, spacing=None):
    """'no_lock' or the (TRE mm, rotation deg) of the pose reported ok."""
    sl = Slice(sim.slice.pixels if pixels is None else pixels, spacing or sim.truth.pixel_spacing_mm,
               slice_thickness_mm=sim.truth.slice_thickness_mm, source="case")
    try:
        reg = register([sl], geom)
    except NoLock as exc:
        assert exc.reason  # always a reason
        return "no_lock"
    return pose_error(reg.T_scanner_from_fiducial, sim.truth.T_scanner_from_fiducial, geom.body.length)


#: The z001 Z-frame's centre in its frame F.
ZF_CENTRE = np.array([0.0, 0.0, 30.0])


def zframe(d_mm: float = 3.0) -> FiducialGeometry:
    """The z001 Z-frame: a 60 mm cube, four axial rods, diagonals on faces x = +30, y = +30, x = -30."""
    a = 30.0
    rods = [("A0", (a, -a, 0), (a, -a, 60)), ("A1", (a, a, 0), (a, a, 60)), ("A2", (-a, a, 0), (-a, a, 60)),
            ("A3", (-a, -a, 0), (-a, -a, 60)), ("Z0", (a, a, 0), (a, -a, 60)), ("Z1", (-a, a, 0), (a, a, 60)),
            ("Z2", (-a, -a, 0), (-a, a, 60))]
    tubes = [LineTube(i, "other", p0, p1, d_mm) for i, p0, p1 in rods]
    return FiducialGeometry("zframe", Body(60.0, 2 * a * math.sqrt(2) + d_mm, 2 * a - d_mm), tuple(tubes))


#: The N-localizer's frame centre in its frame F.
NLOC_CENTRE = np.array([0.0, 0.0, 60.0])
#: Leksell coordinates of the 120 mm box's F: X = 100 + x, Y = 100 - y, Z = 160 - z.
LEKSELL_T = np.array([[1, 0, 0, 100], [0, -1, 0, 100], [0, 0, -1, 160], [0, 0, 0, 1.0]])


def leksell_g_ct(rod_mm: float = 2.0) -> FiducialGeometry:
    """A Leksell-G-like CT N-localizer: two lateral plates at x = +-95 mm, each with two vertical rods 120 mm apart
    (y = -+60) and a diagonal from (y -60, z 0) to (y 60, z 120). F: x patient left, y posterior, z superior,
    origin at the centre of the box's bottom face (so F's axes are the scanner's LPS axes for a supine head)."""
    tubes = []
    for side, sx in (("right", -1), ("left", 1)):
        x = sx * 95.0
        tubes += [LineTube(f"{side}_a", "axial", (x, -60, 0), (x, -60, 120), rod_mm),
                  LineTube(f"{side}_d", "diagonal", (x, -60, 0), (x, 60, 120), rod_mm),
                  LineTube(f"{side}_b", "axial", (x, 60, 0), (x, 60, 120), rod_mm)]
    T = np.array([[1, 0, 0, 100], [0, -1, 0, 100], [0, 0, -1, 160], [0, 0, 0, 1.0]])
    return FiducialGeometry("leksell-g-ct", Body.box(120, (200, 130), (180, 126)), tuple(tubes), family="nlocalizer",
                            frame_coordinates=FrameCoordinates("leksell", T))


def tre_mm(T, T_true, point):
    """The distance (mm) between where two poses put a fiducial point."""
    return float(np.linalg.norm(apply(T, point) - apply(T_true, point)))


def right_or_refused(sl, geom, T_true, point, **options):
    """With the pixel verification on, the pose is within 0.3 mm at ``point`` or refused, never wrong.

    (chic_register.verify.pixels renders sections at the file's diameters: wide
    blobs and imprecise layouts are refused there, which is its decision.)
    """
    try:
        reg = register([sl], geom, **options)
    except NoLock:
        return
    assert tre_mm(reg.T_scanner_from_fiducial, T_true, point) < 0.3


def rician_slice(geom, pose, *, width=1.0, seed=0, distractors=0, missing=(), snr=20.0, render_geom=None):
    """A Rician SNR-20 slice; ``width`` > 1 blurs the blobs to that many times the nominal width."""
    rng = np.random.default_rng(seed)
    sim = simulate_slice(render_geom or geom, *pose, noise="none", distractors=distractors, missing_tubes=missing,
                         rng=rng)
    img = sim.slice.pixels
    if width > 1:
        d_px = geom.tubes[0].diameter / sim.slice.pixel_spacing_mm[0]
        img = ndi.gaussian_filter(img, d_px * math.sqrt(width * width - 1) / 4)  # a disc's 4-sigma width grows so
        img = img / img.max()
    img = add_rician_noise(img, snr, rng)
    return dataclasses.replace(sim.slice, pixels=img), sim.truth.T_scanner_from_fiducial


def blurred_slice(geom, pose, width, snr, seed):
    """A 2 mm slice whose blobs are ``width`` x the channel's (a Gaussian blur of the sharp render); its truth."""
    rng = np.random.default_rng(seed)
    sim = simulate_slice(geom, *pose, slice_thickness_mm=2.0, noise="none", rng=rng)
    img = sim.slice.pixels
    d_px = geom.tubes[0].diameter / sim.slice.pixel_spacing_mm[0]
    sigma_px = d_px * math.sqrt(width * width - 1) / 4  # a disc's 4-sigma width grows to width x
    img = ndi.gaussian_filter(img, sigma_px)
    img = img / img.max()
    if snr is not None:
        img = add_rician_noise(img, snr, rng)
    return dataclasses.replace(sim.slice, pixels=img), sim.truth.T_scanner_from_fiducial, sigma_px


def tre_and_rotation(T, T_true, length_mm):
    """(TRE at the body's centre in mm, rotation error in deg) between two T_scanner_from_fiducial."""
    c = np.array([0.0, 0.0, 0.5 * length_mm, 1.0])
    dR = T[:3, :3].T @ T_true[:3, :3]
    rot = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dR) - 1) / 2))))
    return float(np.linalg.norm((T @ c - T_true @ c)[:3])), rot


def near_end_slice(neuro_geometry, seed=4):
    """A noisy slice near the body's end (helices close to their straight tubes: shared pixels) and its pose."""
    sim = simulate_slice(neuro_geometry, 5.0, 10.0, 30.0, 0.0, slice_thickness_mm=2.0, noise="rician", snr=20,
                         rng=np.random.default_rng(seed))
    T = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
    return np.asarray(sim.slice.pixels, float), T


#: The direction of an oblique volume acquisition.
OBLIQUE = rot_z(25.0) @ rot_y(-12.0)


#: A neuro fiducial's pose in an oblique volume: its axis leans 8 deg from the volume's k axis.
T_TRUE = rigid(OBLIQUE, (4.0, -3.0, 2.0)) @ rigid(rot_z(40.0) @ rot_y(8.0), (0, 0, 0)) @ invert(slice_frame(25.0, 0.0))


def pose_difference(T1, T2, length_mm=50.0, radius_mm=15.0):
    """(largest displacement in mm of points on the body, rotation angle in deg) between two poses."""
    pts = np.array([[radius_mm, 0, 0], [0, radius_mm, 0], [-radius_mm, 0, length_mm],
                    [0, -radius_mm, length_mm], [0, 0, length_mm / 2]])
    d = np.linalg.norm(apply(T1, pts) - apply(T2, pts), axis=1).max()
    dR = T1[:3, :3].T @ T2[:3, :3]
    ang = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dR) - 1) / 2))))
    return float(d), ang


def one_line_error(capsys, prefix: str) -> str:
    """The captured stderr: one line, no traceback, starting with ``prefix``."""
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and "\n" not in err, err
    assert err.startswith(prefix), err
    return err


def edited_dicom(src, dst, **attrs) -> Path:
    """A copy of the DICOM file ``src`` at ``dst`` with attributes set (invalid values too)."""
    ds = pydicom.dcmread(src)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom warns about the invalid DS values we mean to write
        for k, v in attrs.items():
            setattr(ds, k, v)
        ds.save_as(dst)
    return dst


FUZZ = settings(max_examples=40, deadline=20_000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


#: Values a hostile or careless user might put anywhere.
ANY_VALUE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1e-300, 1e300, 1e9, 44.99, 0.01, 1e6, 2**63, -(2**63)]),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.booleans(),
    st.none(),
    st.text(max_size=300),
    st.sampled_from(["1:10", "010", ".inf", "yes", "2024-01-02", "a" * 255, "../x", "x/y", "\x00"]),
    st.lists(st.floats(allow_nan=True), max_size=5),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=3),
)


def assert_one_line(exc, prefix: str) -> None:
    """An exception's message is one line starting with ``prefix``."""
    msg = str(exc)
    assert "\n" not in msg and msg.startswith(prefix), msg


def finite_numbers(obj) -> bool:
    """Every float in a nested structure of dicts, lists and tuples is finite."""
    if isinstance(obj, dict):
        return all(finite_numbers(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return all(finite_numbers(v) for v in obj)
    return not isinstance(obj, float) or math.isfinite(obj)


def modules_after(code: str) -> set[str]:
    """The modules a fresh interpreter holds after running ``code``."""
    probe = code + "\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))\n"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, encoding="utf-8", errors="replace", check=True, timeout=120)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


#: Wide-blob volumes' voxel spacing and shape by design.
WIDE_VOLUME_PROTOCOL = {"neuro": ((0.5, 0.5, 2.0), (128, 128, 40)), "needle": ((0.3, 0.3, 1.0), (128, 128, 40))}


def wide_blob_volume(geom, name, tilt, az, width, seed):
    """A Rician SNR-20 volume of ``geom`` (protocol ``name``) tilted ``tilt`` deg towards azimuth ``az``, its blobs
    ``width`` x the channels' width: (volume, true T_scanner_from_fiducial, the body's centre in F)."""
    spacing, shape = WIDE_VOLUME_PROTOCOL[name]
    L = geom.body.length
    T = rigid(rot_z(az) @ rot_y(tilt), (1.0, -2.0, -L / 2))
    sv = simulate_volume(geom, T, shape, spacing, noise="rician", snr=20, rng=seed, supersample=2,
                         thickness_samples=2, blob_width=width)
    return sv.volume, T, np.array([0.0, 0.0, L / 2])


LEKSELL_T = np.array([[1, 0, 0, 100], [0, -1, 0, 100], [0, 0, -1, 160], [0, 0, 0, 1.0]])
TWO_SHAPE, TWO_PX = (512, 512), 0.5


def three_plate_frame(d_mm: float = 3.0) -> FiducialGeometry:
    """An N-localizer with N's on the right, left and anterior plates (a single slice fixes its pose), in Leksell
    coordinates."""
    tubes = list(leksell_g_ct(d_mm).tubes)  # the Leksell box's lateral plates, and one facing anterior
    tubes += [LineTube("front_a", "axial", (-50, -65, 0), (-50, -65, 120), d_mm),
              LineTube("front_d", "diagonal", (-50, -65, 0), (50, -65, 120), d_mm),
              LineTube("front_b", "axial", (50, -65, 0), (50, -65, 120), d_mm)]
    return FiducialGeometry("three-plate", Body.box(120, (200, 140), (180, 120)), tuple(tubes), family="nlocalizer",
                            frame_coordinates=FrameCoordinates("leksell", LEKSELL_T))


def both_in_one_slice(frame, chic, tilt_deg: float, modality: str, seed: int = 0):
    """One slice through the frame (centred on the scanner origin) and a CHIC on a tool inside it; the truths."""
    T_s_frame = np.eye(4)
    T_s_frame[:3, 3] = [0, 0, -60]
    R = Rotation.from_euler("x", tilt_deg, degrees=True).as_matrix()
    half = np.array([(TWO_SHAPE[1] - 1) / 2 * TWO_PX, (TWO_SHAPE[0] - 1) / 2 * TWO_PX, 0.0])
    T_s_image = np.eye(4)
    T_s_image[:3, :3], T_s_image[:3, 3] = R, -R @ half
    T_image_S = np.eye(4)
    T_image_S[:3, 3] = half
    axis = Rotation.from_euler("y", 12, degrees=True).apply(R[:, 2])
    crossing = R @ np.array([20.0, 15.0, 0.0])
    T_s_chic = np.eye(4)
    T_s_chic[:3, :3] = (Rotation.align_vectors([axis], [[0, 0, 1]])[0].as_matrix()
                        @ Rotation.from_euler("z", 37, degrees=True).as_matrix())
    T_s_chic[:3, 3] = crossing - 25.0 * axis
    img = render_tubes(frame.tubes, invert(T_s_frame) @ T_s_image @ T_image_S, TWO_SHAPE, (TWO_PX, TWO_PX), 2.0)
    img = np.clip(img + render_tubes(chic.tubes, invert(T_s_chic) @ T_s_image @ T_image_S, TWO_SHAPE, (TWO_PX, TWO_PX), 2.0), 0, 1)
    rng = np.random.default_rng(seed)
    if modality == "MR":
        img = add_rician_noise(img, 20.0, rng)
    else:  # Hounsfield units: air, contrast-filled rods, Gaussian noise
        img = -1000.0 + 2500.0 * img + rng.normal(0.0, 20.0, img.shape)
    sl = Slice(img, (TWO_PX, TWO_PX), T_s_image[:3, 3].copy(), R[:, 0].copy(), R[:, 1].copy(), 2.0, f"two-{modality}")
    return sl, T_s_frame, T_s_chic
