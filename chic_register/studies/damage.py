"""Damaged slices for the false-lock hunts: the damage kinds real scans show.

A hunt case (:class:`Case`) is a simulated slice of a fiducial at a random pose
over and beyond its usable envelope (depth from -15 % to 115 % of the body
length, tilt 0-80 deg, any azimuth and twist, random pixel size, field of
view, slice thickness, centre offset and Rician SNR) with one damage kind of
:data:`MUTATIONS`: a tool in the bore, distractors, erased tubes, fluid on the
tubes' circle, zeroed pixels, a rotated or flipped image, a wrong pixel
spacing, a motion ghost, coil shading, RF stripes. :func:`make_case` draws case
``index`` of a hunt seeded ``seed`` (each case its own random stream,
``default_rng([seed, index])``), :func:`build_case` renders it to the
:class:`~chic_register.model.slices.Slice` to solve with its true pose, and
:func:`solve_and_judge` registers it and judges the outcome against the
truth: ``ok``, ``false_lock`` (more than :data:`FALSE_LOCK_MM` at the frame
centre or :data:`FALSE_LOCK_DEG` off), ``no_lock`` or ``crash``.

Two further sets of damage apply to a case's ``noisy`` variant (Rician noise,
no other damage):

- :data:`UNLISTED_KINDS` (:func:`unlisted_damage`, :func:`unlisted_slice`):
  what a scanner or an image pipeline may do to a slice beyond that list: hot
  pixels, motion blur, Gibbs ringing, wrap-around, quantisation, a 2x zoom,
  NaN pixels, a subtracted offset, k-space spikes, partial Fourier, a resampled
  rotation, a sub-pixel shift, an 8-bit window, inverted contrast, signed
  (phase-ramped) data, a susceptibility void, an EPI Nyquist ghost, gradient
  non-linearity, block-DCT compression;
- :data:`PRINT_KINDS` (:func:`print_damage`, :func:`run_print_case`): what a
  print and its geometry file get wrong (air bubbles, a water bath, a dim
  fill, a scale error, a stale or another design's geometry file).

The benchmarks ``benchmarks/hunt.py``, ``hunt_unlisted.py`` and
``hunt_print.py`` run thousands of these cases; the tests rebuild the ones
that once locked wrong. Every random draw is part of a case's definition: the
functions here draw in a fixed order, so a case is the same slice on every
run.
"""

from __future__ import annotations

import dataclasses
import math
import time
import traceback
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from scipy.fft import dctn, idctn

from chic_register.errors import NoLock
from chic_register.imaging.render import render_tubes
from chic_register.imaging.simulate import add_rician_noise, simulate_slice
from chic_register.model.envelope import plane_status
from chic_register.model.pose import invert, slice_frame
from chic_register.model.slices import Slice
from chic_register.model.tube_model import plane_crossings, prepare_geometry
from chic_register.model.tubes import LineTube
from chic_register.pipeline.register import register

#: A pose reported ok further than this from the truth (mm, at the frame centre) is a false lock.
FALSE_LOCK_MM = 0.5
#: A pose reported ok turned further than this from the truth (deg) is a false lock.
FALSE_LOCK_DEG = 0.5
#: The hunt's damage kinds, one per case.
MUTATIONS = ("clean", "noisy", "thick_slab", "low_snr", "tool_in_bore", "distractors", "erased_tubes",
             "circle_blobs", "zeroed_pixels", "rotated_flipped", "wrong_spacing", "ghosting", "bias_field",
             "stripes")
#: Damage after which no pose is right: every ok is checked against the truth all the same.
REFUSE_EXPECTED = ("wrong_spacing",)


@dataclass(frozen=True)
class Case:
    """One hunt case: everything needed to rebuild its slice."""

    index: int
    geometry: str
    depth_mm: float
    tilt_deg: float
    azimuth_deg: float
    twist_deg: float
    pixel_mm: float
    size: int
    slice_thickness_mm: float
    offset_mm: tuple
    snr: float
    mutation: str
    mutation_seed: int
    blob_width: float = 1.0  # every blob this x its tube's width (--blob-width; 1: as drawn)


def make_case(index: int, seed: int, geometries: dict, blob_width=(1.0, 1.0)) -> Case:
    """The ``index``-th case of the hunt seeded ``seed`` (independent of every other case).

    ``geometries``: the fiducials by name (the case picks one). ``blob_width``
    (lo, hi): draw every blob a factor from this range x its tube's width (its
    own random stream, so the rest of the case is the same as without it)."""
    rng = np.random.default_rng([seed, index])
    lo, hi = (float(v) for v in blob_width)
    width = float(np.random.default_rng([seed, index, 1]).uniform(lo, hi)) if hi > lo else lo
    name = sorted(geometries)[int(rng.integers(len(geometries)))]
    geom = geometries[name]
    L = geom.body.length
    d = min(t.diameter for t in geom.tubes)
    mutation = MUTATIONS[int(rng.integers(len(MUTATIONS)))]
    pixel = float(rng.uniform(0.12, 0.36) * d)  # 3 mm tubes: 0.36-1.08 mm pixels; 1.6 mm: 0.19-0.58
    od = geom.body.outer_diameter
    fov = float(rng.uniform(2.2, 6.0) * od)
    thick = float(rng.choice([0.0, rng.uniform(0.3, 1.0) * d]))
    if mutation == "thick_slab":
        thick = float(rng.uniform(1.0, 2.0) * d)
    snr = float(rng.uniform(12.0, 60.0))
    if mutation == "low_snr":
        snr = float(rng.uniform(4.0, 10.0))
    return Case(
        index=index, geometry=name,
        depth_mm=float(rng.uniform(-0.15, 1.15) * L), tilt_deg=float(rng.uniform(0.0, 80.0)),
        azimuth_deg=float(rng.uniform(-180, 180)), twist_deg=float(rng.uniform(-180, 180)),
        pixel_mm=pixel, size=int(max(32, round(fov / pixel))), slice_thickness_mm=thick,
        offset_mm=(float(rng.uniform(-0.3, 0.3) * od), float(rng.uniform(-0.3, 0.3) * od)),
        snr=snr, mutation=mutation, mutation_seed=int(rng.integers(2**31)), blob_width=width,
    )


def noisy_case(index: int, seed: int, geometries: dict) -> Case:
    """Case ``index`` of the hunt seeded ``seed`` with its damage replaced by ``noisy`` (Rician noise alone): the
    slice the unlisted and print damage start from."""
    return dataclasses.replace(make_case(index, seed, geometries), mutation="noisy")


def index_map(op, shape):
    """Affine map new pixel (row, col) -> old (row, col) of an array operation ``op``: (A (2, 2), t (2,))."""
    idx = op(np.arange(shape[0] * shape[1]).reshape(shape))
    old = [np.array(divmod(int(idx[r, c]), shape[1]), float) for r, c in ((0, 0), (1, 0), (0, 1))]
    return np.stack([old[1] - old[0], old[2] - old[0]], axis=1), old[0]


def T_old_from_new(A, t, spacing_old, spacing_new):
    """Image-frame transform (4x4) of a pixel re-indexing (row/col maps ``A``, ``t``): new mm -> old mm."""
    # image mm: x = col * cs, y = row * rs; new (x', y') -> new (r', c') -> old (r, c) -> old (x, y)
    rs, cs = spacing_old
    rs2, cs2 = spacing_new
    to_rc_new = np.array([[0.0, 1.0 / rs2], [1.0 / cs2, 0.0]])  # (x', y') -> (r', c')
    to_xy_old = np.array([[0.0, cs], [rs, 0.0]])  # (r, c) -> (x, y)
    L = to_xy_old @ A @ to_rc_new
    T = np.eye(4)
    T[:2, :2] = L
    T[2, 2] = round(float(np.linalg.det(L)))  # a mirror in the plane = the plane seen from its other side
    T[:2, 3] = to_xy_old @ t
    return T


def build_case(case: Case, geom):
    """``(Slice to solve, true T_scanner_from_fiducial, in_envelope)`` of a case.

    ``in_envelope``: the true plane passes the design's plane checks
    (:func:`chic_register.model.envelope.plane_status` at the slice's pixel size
    and thickness) and every tube's crossing lies in the image."""
    rng = np.random.default_rng(case.mutation_seed)
    m = case.mutation
    d = min(t.diameter for t in geom.tubes)
    extra = {}
    if m == "tool_in_bore":
        extra["bore_signal"] = float(rng.uniform(0.4, 1.2))
    if m == "distractors":
        extra["distractors"] = int(rng.integers(2, 12))
    if m == "erased_tubes":
        extra["missing_tubes"] = tuple(rng.choice(geom.ids, size=int(rng.integers(1, 4)), replace=False))
    px = (case.pixel_mm, case.pixel_mm)
    shape = (case.size, case.size)
    sim = simulate_slice(geom, case.depth_mm, case.tilt_deg, case.azimuth_deg, case.twist_deg, shape=shape,
                         pixel_spacing_mm=px, slice_thickness_mm=case.slice_thickness_mm,
                         center_offset_mm=case.offset_mm, image_position=(0.0, 0.0, 0.0), rng=rng,
                         supersample=3, thickness_samples=5, blob_width=case.blob_width, **extra)
    img = np.array(sim.slice.pixels, float)
    truth = sim.truth
    T_true = np.array(truth.T_scanner_from_fiducial, float)
    if m == "circle_blobs":  # tube-sized bright blobs where the plane meets the tubes' circle
        T = slice_frame(case.depth_mm, case.tilt_deg, case.azimuth_deg, case.twist_deg)
        n = T[:3, 2]
        R = float(np.median([math.hypot(*np.mean([t.points(0.0)[0], t.points(1.0)[0]], axis=0)[:2])
                             for t in geom.tubes]))
        blobs = []
        for _ in range(int(rng.integers(1, 3))):
            th = rng.uniform(0, 2 * math.pi)
            if abs(n[2]) < 1e-6:
                continue
            z = (n @ T[:3, 3] - R * (n[0] * math.cos(th) + n[1] * math.sin(th))) / n[2]
            p = np.array([R * math.cos(th), R * math.sin(th), z])
            blobs.append(LineTube("blob", "other", tuple(p - 0.5 * d * n), tuple(p + 0.5 * d * n), d))
        if blobs:
            img = np.maximum(img, render_tubes(blobs, T, shape, px, case.slice_thickness_mm, truth.center_px,
                                               supersample=3, thickness_samples=3))
    if m == "ghosting":  # motion ghost: a shifted copy along the phase-encoding direction
        axis = int(rng.integers(2))
        img = img + float(rng.uniform(0.1, 0.45)) * np.roll(img, case.size // int(rng.integers(2, 5)), axis=axis)
    if m == "bias_field":  # smooth receive-coil shading
        yy, xx = np.mgrid[-1:1:complex(0, case.size), -1:1:complex(0, case.size)]
        a, b, c = rng.uniform(-0.5, 0.5, 3)
        img = img * np.clip(1.0 + a * xx + b * yy + c * (xx * xx + yy * yy), 0.3, 2.0)
    if m != "clean":
        img = add_rician_noise(img, case.snr, rng)
    if m == "stripes":  # RF spikes / zipper lines
        for _ in range(int(rng.integers(1, 6))):
            k = int(rng.integers(case.size))
            if rng.random() < 0.5:
                img[k, :] += rng.uniform(0.3, 1.0)
            else:
                img[:, k] += rng.uniform(0.3, 1.0)
    if m == "zeroed_pixels":
        img[rng.random(img.shape) < rng.uniform(0.1, 0.4)] = 0.0
    spacing = px
    if m == "rotated_flipped":
        ops = [lambda a: np.rot90(a, 1), lambda a: np.rot90(a, 2), lambda a: np.rot90(a, 3), np.fliplr, np.flipud,
               lambda a: np.rot90(np.fliplr(a))]
        op = ops[int(rng.integers(len(ops)))]
        A, t = index_map(op, img.shape)
        img = np.ascontiguousarray(op(img))
        T_on = T_old_from_new(A, t, px, spacing)
        T_true = invert(T_on) @ T_true
    if m == "wrong_spacing":
        e = rng.uniform(0.06, 0.25, 2) * rng.choice([-1.0, 1.0], 2)
        if rng.random() < 0.5:
            e[int(rng.integers(2))] = 0.0
        spacing = (px[0] * (1 + e[0]), px[1] * (1 + e[1]))
    sl = Slice(img, spacing, slice_thickness_mm=case.slice_thickness_mm, source=f"case{case.index}")
    status = plane_status(geom, case.depth_mm, case.tilt_deg, case.azimuth_deg, case.pixel_mm,
                          case.slice_thickness_mm)
    rows, cols = shape
    margin = d / case.pixel_mm
    seen = [k for k, (r, c) in truth.centres_px.items()
            if margin <= r <= rows - 1 - margin and margin <= c <= cols - 1 - margin]
    in_env = status.ok and len(seen) == len(geom.tubes) - len(truth.missing_tubes)
    return sl, T_true, in_env


def pose_error(T_est, T_true, length_mm: float):
    """(TRE at the frame centre (0, 0, L/2) in mm, rotation error in deg) between two T_scanner_from_fiducial."""
    c = np.array([0.0, 0.0, 0.5 * length_mm, 1.0])
    tre = float(np.linalg.norm((T_est @ c - T_true @ c)[:3]))
    dR = T_est[:3, :3].T @ T_true[:3, :3]
    rot = math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(dR)) - 1) / 2))))
    return tre, rot


def solve_and_judge(sl, geom, T_true, ndigits: int | None = None, solve_geom=None, options: dict | None = None) -> dict:
    """Register one slice (with ``solve_geom``, default ``geom``; ``options``: fields of
    :class:`~chic_register.options.SolveOptions`) and judge it against the truth: ``outcome``
    (``ok`` / ``false_lock``, beyond FALSE_LOCK_MM or FALSE_LOCK_DEG / ``no_lock`` with its ``reason`` / ``crash``
    with ``error`` and ``trace``) and the errors ``tre_mm``, ``rot_deg`` (rounded to ``ndigits`` when given)."""
    try:
        reg = register([sl], solve_geom or geom, **(options or {}))
    except NoLock as exc:
        return {"outcome": "no_lock", "reason": exc.reason}
    except Exception as exc:  # noqa: BLE001 - every other exception is a crash to report
        return {"outcome": "crash", "error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc(limit=4)}
    tre, rot = pose_error(reg.T_scanner_from_fiducial, T_true, geom.body.length)
    false = tre > FALSE_LOCK_MM or rot > FALSE_LOCK_DEG
    if ndigits is not None:
        tre, rot = round(tre, ndigits), round(rot, ndigits)
    return {"outcome": "false_lock" if false else "ok", "tre_mm": tre, "rot_deg": rot}


def run_case(case: Case, geometries: dict, options: dict | None = None) -> dict:
    """Solve one case (``options``: fields of :class:`~chic_register.options.SolveOptions`); its outcome (``ok`` /
    ``false_lock`` / ``no_lock`` / ``crash``, or ``setup_error`` when the case itself could not be built), errors
    and CPU time (``cpu_s``)."""
    geom = geometries[case.geometry]
    c0 = time.process_time()
    out = {"index": case.index, "geometry": case.geometry, "mutation": case.mutation}
    try:
        sl, T_true, in_env = build_case(case, geom)
    except Exception:  # the hunt's own fault, not the solver's: reported apart
        out.update(outcome="setup_error", error=traceback.format_exc(limit=3))
        return out
    out["in_envelope"] = bool(in_env)
    out.update(solve_and_judge(sl, geom, T_true, options=options))
    out["cpu_s"] = time.process_time() - c0
    return out


# ----------------------------------------------------------------------------- damage the hunt does not draw

#: The unlisted damage kinds (:func:`unlisted_damage`).
UNLISTED_KINDS = ("specks", "motion_blur", "gibbs", "wrap", "quantize", "zoom2", "nan_pixels", "offset_negative",
                  "aniso_blur", "spike_kspace", "partial_fourier", "rotate_resample", "subpixel_shift", "clip_8bit",
                  "inverted", "signed_phase", "susceptibility_void", "nyquist_ghost", "radial_warp", "jpeg_blocks")


def unlisted_damage(kind: str, img: np.ndarray, spacing, rng: np.random.Generator, centres_rc=None):
    """``(pixels, pixel spacing, T_old_from_new)`` of a slice after one damage ``kind`` of :data:`UNLISTED_KINDS`.

    ``specks``: hot pixels; ``motion_blur``: a 3-8 pixel box blur along rows
    or columns; ``gibbs``: k-space cut to 25-60 % along one axis; ``wrap``: a
    fold-over strip; ``quantize``: 4-15 levels; ``zoom2``: a 2x bilinear zoom
    declared with half the spacing; ``nan_pixels``; ``offset_negative``: a
    background subtracted; ``aniso_blur``; ``spike_kspace``: a stripe pattern
    over the whole image; ``partial_fourier``: 55-75 % of k-space along one
    axis, the rest zero-filled; ``rotate_resample``: an in-plane rotation by a
    non-right angle, bilinear (corners zero); ``subpixel_shift``: by Fourier
    interpolation; ``clip_8bit``: a window saturating the fluid (in half the
    cases clipping the background to 0); ``inverted``; ``signed_phase``: the
    real part of a complex image under a phase ramp; ``susceptibility_void``: a
    dark disc beside one tube with a bright crescent; ``nyquist_ghost``: an EPI
    half-field copy with alternating line sign; ``radial_warp``: a 1-3 % scale
    error at the image edge; ``jpeg_blocks``: 8x8 block DCT quantisation.

    ``T_old_from_new``: for a damage that moves the image content (rotation,
    shift), the image-frame transform (4x4, mm) from the new pixels' frame to
    the old one (:func:`T_old_from_new`), else None. ``centres_rc``: the
    tubes' true centres (pixels), for damage placed beside a tube."""
    img = np.array(img, float)
    T = None
    H, W = img.shape
    level = float(np.percentile(img, 99.5))  # about the fluid's level
    if kind == "specks":
        img[rng.random(img.shape) < rng.uniform(0.01, 0.1)] = img.max() * rng.uniform(0.5, 1.5)
    elif kind == "motion_blur":
        k = np.ones((1, int(rng.integers(3, 9))))
        img = ndi.convolve(img, (k if rng.random() < 0.5 else k.T) / k.size, mode="nearest")
    elif kind == "gibbs":
        F = np.fft.fftshift(np.fft.fft2(img))
        h = img.shape[0]
        keep = rng.uniform(0.25, 0.6)
        cut = np.zeros(F.shape, bool)
        cut[int(h / 2 - keep * h / 2):int(h / 2 + keep * h / 2), :] = True
        img = np.abs(np.fft.ifft2(np.fft.ifftshift(F * cut)))
    elif kind == "wrap":
        s = int(img.shape[0] * rng.uniform(0.2, 0.45))
        img[-s:] += img[:s].copy()
    elif kind == "quantize":
        levels = int(rng.integers(4, 16))
        img = np.round(img / img.max() * levels) / levels
    elif kind == "zoom2":
        img = ndi.zoom(img, 2, order=1)
        spacing = (spacing[0] / 2, spacing[1] / 2)
    elif kind == "nan_pixels":
        img[rng.random(img.shape) < rng.uniform(0.001, 0.05)] = np.nan
    elif kind == "offset_negative":
        img = img - rng.uniform(0.2, 1.0) * np.median(img)
    elif kind == "aniso_blur":
        img = ndi.gaussian_filter(img, (rng.uniform(0, 0.5), rng.uniform(1.0, 3.0)))
    elif kind == "spike_kspace":
        F = np.fft.fft2(img)
        F[rng.integers(0, img.shape[0]), rng.integers(0, img.shape[1])] += rng.uniform(0.05, 0.3) * np.abs(F).max()
        img = np.abs(np.fft.ifft2(F))
    elif kind == "partial_fourier":  # zero-filled partial Fourier along one axis (one side of k-space)
        axis = int(rng.integers(2))
        F = np.fft.fftshift(np.fft.fft2(img))
        n = F.shape[axis]
        cut = int(round(n * (1.0 - rng.uniform(0.55, 0.75))))
        sl = [slice(None)] * 2
        sl[axis] = slice(0, cut) if rng.random() < 0.5 else slice(n - cut, n)
        F[tuple(sl)] = 0.0
        img = np.abs(np.fft.ifft2(np.fft.ifftshift(F)))
    elif kind == "rotate_resample":  # in-plane rotation by a non-right angle, bilinear, about the image centre
        a = math.radians(rng.uniform(3.0, 87.0) * rng.choice([-1.0, 1.0]))
        A = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        c = np.array([(H - 1) / 2, (W - 1) / 2])
        t = c - A @ c
        img = ndi.affine_transform(img, A, offset=t, order=1, mode="constant", cval=0.0)
        T = T_old_from_new(A, t, spacing, spacing)
    elif kind == "subpixel_shift":  # a sub-pixel translation by Fourier interpolation
        d = rng.uniform(-1.0, 1.0, 2)
        img = np.fft.ifft2(ndi.fourier_shift(np.fft.fft2(img), d)).real
        T = T_old_from_new(np.eye(2), -d, spacing, spacing)
    elif kind == "clip_8bit":  # a display window saturating the fluid, stored as 8 bits
        top = rng.uniform(0.3, 0.9) * level
        bottom = rng.uniform(0.0, 3.0) * float(np.median(img)) if rng.random() < 0.5 else 0.0
        img = np.round(np.clip((img - bottom) / (top - bottom), 0.0, 1.0) * 255.0)
    elif kind == "inverted":
        img = level - img
    elif kind == "signed_phase":  # the real part of a complex image whose phase ramps across the field
        yy, xx = np.mgrid[0:H, 0:W]
        cycles = rng.uniform(0.2, 1.5)
        th = rng.uniform(0, 2 * math.pi)
        phase = 2 * math.pi * cycles * (xx * math.cos(th) / W + yy * math.sin(th) / H) + rng.uniform(0, 2 * math.pi)
        img = img * np.cos(phase)
    elif kind == "susceptibility_void":  # a dark disc beside one tube, signal piled up in a crescent on one side
        if centres_rc is not None and len(centres_rc):
            r0, c0 = centres_rc[int(rng.integers(len(centres_rc)))]
            d_px = float(rng.uniform(3.0, 8.0))
            ang = rng.uniform(0, 2 * math.pi)
            rc = np.array([r0, c0]) + rng.uniform(0.5, 1.5) * d_px * np.array([math.sin(ang), math.cos(ang)])
            yy, xx = np.mgrid[0:H, 0:W]
            rr = np.hypot(yy - rc[0], xx - rc[1])
            sigma_bg = float(np.median(img)) / 1.1774
            void = rr < d_px
            img[void] = rng.rayleigh(max(sigma_bg, 1e-6), int(void.sum()))
            side = np.cos(np.arctan2(yy - rc[0], xx - rc[1]) - rng.uniform(0, 2 * math.pi))
            img += rng.uniform(0.3, 1.0) * level * np.exp(-0.5 * ((rr - d_px) / 1.0) ** 2) * np.clip(side, 0, None) ** 2
    elif kind == "nyquist_ghost":  # EPI: a half-field copy, every other line of opposite sign, added coherently
        axis = int(rng.integers(2))
        sign = np.where(np.arange(img.shape[axis]) % 2 == 0, 1.0, -1.0)
        sign = sign[:, None] if axis == 0 else sign[None, :]
        img = np.abs(img + rng.uniform(0.05, 0.3) * sign * np.roll(img, img.shape[axis] // 2, axis=axis))
    elif kind == "radial_warp":  # gradient non-linearity: scale error e (1-3 %) at the image's edge, ~ r^2
        e = rng.uniform(0.01, 0.03) * rng.choice([-1.0, 1.0])
        c = np.array([(H - 1) / 2, (W - 1) / 2])
        yy, xx = np.mgrid[0:H, 0:W].astype(float)
        f = 1.0 + e * ((yy - c[0]) ** 2 + (xx - c[1]) ** 2) / (0.25 * (H * H + W * W))
        img = ndi.map_coordinates(img, [c[0] + (yy - c[0]) * f, c[1] + (xx - c[1]) * f], order=1, mode="nearest")
    elif kind == "jpeg_blocks":  # 8x8 block DCT, coarser steps at higher frequencies, as a lossy codec
        hb, wb = H // 8, W // 8
        blocks = img[:hb * 8, :wb * 8].reshape(hb, 8, wb, 8).swapaxes(1, 2)
        u = np.arange(8)
        step = rng.uniform(0.01, 0.08) * level * (1.0 + u[:, None] + u[None, :])
        D = dctn(blocks, axes=(2, 3), norm="ortho")
        blocks = idctn(np.round(D / step) * step, axes=(2, 3), norm="ortho")
        img[:hb * 8, :wb * 8] = blocks.swapaxes(1, 2).reshape(hb * 8, wb * 8)
    return img, spacing, T


def true_centres_rc(geom, T_scanner_from_fiducial, spacing) -> np.ndarray:
    """(K, 2) pixel (row, col) of the tubes' centreline crossings with the true plane (the image frame is the
    scanner's)."""
    q, _, _, found = plane_crossings(prepare_geometry(geom)[0], invert(T_scanner_from_fiducial))
    return np.stack([q[found, 1] / spacing[0], q[found, 0] / spacing[1]], axis=1)


def unlisted_slice(index: int, seed: int, kind: str, geometries: dict):
    """``(Slice, true T_scanner_from_fiducial, case, in_envelope)`` of case ``index`` of the hunt seeded ``seed``
    (its ``noisy`` variant, a :class:`Case`) after the unlisted damage ``kind`` (drawn from ``default_rng([seed,
    index, 99])``); the truth moves with a damage that moves the image content."""
    case = noisy_case(index, seed, geometries)
    geom = geometries[case.geometry]
    sl, T_true, in_env = build_case(case, geom)
    img, spacing, T_on = unlisted_damage(kind, sl.pixels, sl.pixel_spacing_mm,
                                         np.random.default_rng([seed, index, 99]),
                                         true_centres_rc(geom, T_true, sl.pixel_spacing_mm))
    if T_on is not None:
        T_true = invert(T_on) @ T_true
    return Slice(img, spacing, slice_thickness_mm=sl.slice_thickness_mm, source=f"case{index}"), T_true, case, in_env


# ----------------------------------------------------------------------------- what a print gets wrong

#: What a print and its geometry file get wrong (:func:`print_damage`, :func:`run_print_case`).
PRINT_KINDS = ("bubble", "water_bath", "dim_tube", "scale", "helix_offset", "other_design")
#: The size of a kind's error when none is given: ``scale`` a fraction, ``helix_offset`` degrees.
PRINT_DEFAULT_AMOUNT = {"scale": 0.002, "helix_offset": 0.5}
#: A section's neighbourhood (tube radii) that a bubble or a dim fill reaches.
REACH_RADII = 2.5


def print_damage(kind: str, img: np.ndarray, sl, geom, T_true: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The slice's pixels after ``kind`` of :data:`PRINT_KINDS` (``scale``, ``helix_offset`` and ``other_design``
    leave them alone).

    ``bubble``: one or two sections partly dark (air in the channel: the part
    beyond a chord 0.5 radii before to 0.8 radii past the centre, background
    noise); ``water_bath``: water at 20-100 % of the fluid's level outside the
    body, in its bore and beyond its end faces; ``dim_tube``: one tube at
    20-60 % of the others' signal."""
    img = np.array(img, float)
    H, W = img.shape
    level = float(np.percentile(img, 99.5))  # about the fluid's level
    sigma = float(np.median(img)) / 1.1774  # the Rayleigh background's scale
    centres = true_centres_rc(geom, T_true, sl.pixel_spacing_mm)
    r_px = 0.5 * geom.tubes[0].diameter / float(min(sl.pixel_spacing_mm))
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    if kind == "bubble" and len(centres):
        for _ in range(int(rng.integers(1, 3))):
            r0, c0 = centres[int(rng.integers(len(centres)))]
            ang, off = rng.uniform(0, 2 * math.pi), rng.uniform(-0.5, 0.8) * r_px
            air = (np.hypot(yy - r0, xx - c0) < REACH_RADII * r_px) & (
                (yy - r0) * math.sin(ang) + (xx - c0) * math.cos(ang) > off)
            img[air] = rng.rayleigh(max(sigma, 1e-6), int(air.sum()))
    elif kind == "dim_tube" and len(centres):
        r0, c0 = centres[int(rng.integers(len(centres)))]
        near = np.hypot(yy - r0, xx - c0) < REACH_RADII * r_px
        img[near] *= rng.uniform(0.2, 0.6)
    elif kind == "water_bath":
        P = sl.pixel_to_scanner(yy.ravel(), xx.ravel())
        T_fs = invert(T_true)
        F = P @ T_fs[:3, :3].T + T_fs[:3, 3]  # the pixels in the fiducial's frame
        r, z = np.hypot(F[:, 0], F[:, 1]), F[:, 2]
        b = geom.body
        water = ((r > 0.5 * b.outer_diameter) | (r < 0.5 * b.inner_diameter) | (z < 0) | (z > b.length)).reshape(H, W)
        n = int(water.sum())
        img[water] = np.abs(rng.uniform(0.2, 1.0) * level + rng.normal(0, sigma, n) + 1j * rng.normal(0, sigma, n))
    return img


def other_design_geometries(geometries: dict) -> dict:
    """For ``other_design``: each geometry's name mapped to the next design's geometry (in name order), the wrong file
    its slices are solved with."""
    names = sorted(geometries)
    return {name: geometries[names[(i + 1) % len(names)]] for i, name in enumerate(names)}


def print_scaled(sl: Slice, T_scanner_from_fiducial: np.ndarray, geom, amount: float) -> Slice:
    """``sl`` as the image of a print ``amount`` (a fraction) larger than its geometry file: its pixel spacing
    declared that much too large about the foot of the fiducial's centre on the slice's plane, which stays where
    it is (a gradient calibration error scales about the isocentre instead: :mod:`chic_register.imaging.scanner`)."""
    origin = np.asarray(sl.origin_mm, float)
    centre = (np.asarray(T_scanner_from_fiducial, float) @ np.array([0.0, 0.0, 0.5 * geom.body.length, 1.0]))[:3]
    n = np.asarray(sl.normal, float)
    pivot = centre - float((centre - origin) @ n) * n
    return dataclasses.replace(sl, pixel_spacing_mm=tuple(v * (1 + amount) for v in sl.pixel_spacing_mm),
                               origin_mm=pivot - (1 + amount) * (pivot - origin))


def run_print_case(index: int, seed: int, kind: str, amount: float, geometries: dict, wrong: dict | None = None,
                   options: dict | None = None) -> dict:
    """One case of the print hunt: case ``index`` of the hunt seeded ``seed`` (its ``noisy`` variant) changed by
    ``kind`` (drawn from ``default_rng([seed, index, 7])``; ``scale``: the pixel spacing declared ``amount`` too
    large about the fiducial's centre, the image of a print that much larger), solved with ``wrong[geometry]`` when given (``helix_offset``, ``other_design``) and ``options`` (fields of :class:`~chic_register.options.SolveOptions`), judged to 4 digits."""
    case = noisy_case(index, seed, geometries)
    geom = geometries[case.geometry]
    out = {"index": index, "geometry": case.geometry}
    try:
        sl, T_true, in_env = build_case(case, geom)
        img = print_damage(kind, sl.pixels, sl, geom, T_true, np.random.default_rng([seed, index, 7]))
    except Exception:  # the hunt's own fault, not the solver's: reported apart
        out.update(outcome="setup_error", error=traceback.format_exc(limit=3), in_envelope=False)
        return out
    damaged = Slice(img, sl.pixel_spacing_mm, origin_mm=sl.origin_mm, col_dir=sl.col_dir, row_dir=sl.row_dir,
                    slice_thickness_mm=sl.slice_thickness_mm, source=f"case{index}")
    if kind == "scale":
        damaged = print_scaled(damaged, T_true, geom, amount)
    out.update(solve_and_judge(damaged, geom, T_true, ndigits=4, solve_geom=(wrong or {}).get(case.geometry),
                               options=options))
    out.update(tilt_deg=round(case.tilt_deg, 1), in_envelope=bool(in_env))
    return out
