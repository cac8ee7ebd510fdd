"""False-lock hunt on damage the main hunt does not draw: what a real scanner or a pipeline may do to a slice.

    .venv/bin/python benchmarks/hunt_unlisted.py [--cases 1000] [--seed 7] [--workers 2]

Each case is one of ``benchmarks/hunt.py``'s random slices (its ``noisy``
variant: Rician noise, no other damage), then one of :data:`KINDS` applied
(case ``i`` gets kind ``i % len(KINDS)``): bright specks (hot pixels), motion
blur along rows or columns, Gibbs ringing (k-space cut to 25-60 % along one
axis), a fold-over (wrap-around) strip, quantisation to 4-15 levels, a 2x
bilinear zoom declared with half the spacing (a scanner's interpolated
matrix), NaN pixels, a negative offset (a background subtracted), an
anisotropic blur, a k-space spike (a stripe pattern over the whole image);
and, added later: partial Fourier (55-75 % of k-space along one axis, the
rest zero-filled), an in-plane rotation by a non-right angle with bilinear
resampling (corners zero; the truth turned with it), a sub-pixel shift by
Fourier interpolation (the truth shifted with it), an 8-bit window that
saturates the fluid (and in half the cases clips the background to 0),
inverted contrast, the real part of a complex image under a phase ramp
(signed data), a susceptibility void beside one tube (a dark disc with a
bright crescent), an EPI Nyquist ghost (a half-field copy with alternating
line sign, added coherently), a smooth radial warp (gradient non-linearity:
1-3 % scale error at the image edge; the truth unchanged) and JPEG-like 8x8
block DCT quantisation. Reports per kind ok / false lock / no_lock / crash
(as hunt.py: a false lock is ``ok`` more than 0.5 mm or 0.5 deg from the
truth) and lists the false locks, crashes and cases over 8 s of wall time.
Each worker is limited to 3 GiB of address space, so a runaway allocation
is a crash here. Exit status 1 on a crash.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import collections  # noqa: E402
import dataclasses  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import hunt  # noqa: E402

KINDS = ("specks", "motion_blur", "gibbs", "wrap", "quantize", "zoom2", "nan_pixels", "offset_negative",
         "aniso_blur", "spike_kspace", "partial_fourier", "rotate_resample", "subpixel_shift", "clip_8bit", "inverted",
         "signed_phase", "susceptibility_void", "nyquist_ghost", "radial_warp", "jpeg_blocks")
MEMORY_LIMIT_BYTES = 3 * 2**30
SLOW_S = 8.0


def damage(kind: str, img: np.ndarray, spacing, rng: np.random.Generator, centres_rc=None):
    """``(pixels, pixel spacing, T_old_from_new)`` of a slice after one damage ``kind`` (see the module docstring).

    ``T_old_from_new``: for a damage that moves the image content (rotation,
    shift), the image-frame transform (4x4, mm) from the new pixels' frame to
    the old one (:func:`hunt._T_old_from_new`), else None. ``centres_rc``: the
    tubes' true centres (pixels), for damage placed beside a tube."""
    from scipy import ndimage as ndi

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
        T = hunt._T_old_from_new(A, t, spacing, spacing)
    elif kind == "subpixel_shift":  # a sub-pixel translation by Fourier interpolation
        d = rng.uniform(-1.0, 1.0, 2)
        img = np.fft.ifft2(ndi.fourier_shift(np.fft.fft2(img), d)).real
        T = hunt._T_old_from_new(np.eye(2), -d, spacing, spacing)
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
        from scipy.fft import dctn, idctn

        hb, wb = H // 8, W // 8
        blocks = img[:hb * 8, :wb * 8].reshape(hb, 8, wb, 8).swapaxes(1, 2)
        u = np.arange(8)
        step = rng.uniform(0.01, 0.08) * level * (1.0 + u[:, None] + u[None, :])
        D = dctn(blocks, axes=(2, 3), norm="ortho")
        blocks = idctn(np.round(D / step) * step, axes=(2, 3), norm="ortho")
        img[:hb * 8, :wb * 8] = blocks.swapaxes(1, 2).reshape(hb * 8, wb * 8)
    return img, spacing, T


def _init() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))
    hunt._init(None)


def true_centres_rc(geom, T_scanner_from_fiducial, spacing) -> np.ndarray:
    """(K, 2) pixel (row, col) of the tubes' centreline crossings with the true plane (the image frame is the
    scanner's)."""
    from chic_register.model.pose import invert
    from chic_register.model.tube_model import plane_crossings, prepare_geometry

    q, _, _, found = plane_crossings(prepare_geometry(geom)[0], invert(T_scanner_from_fiducial))
    return np.stack([q[found, 1] / spacing[0], q[found, 0] / spacing[1]], axis=1)


def run_case(index: int, seed: int) -> dict:
    """One case: its damage kind, outcome, errors and wall time."""
    from chic_register.model.pose import invert
    from chic_register.model.slices import Slice

    geoms = hunt._GEOMS
    case = dataclasses.replace(hunt.make_case(index, seed, geoms), mutation="noisy")
    geom = geoms[case.geometry]
    kind = KINDS[index % len(KINDS)]
    out = {"index": index, "kind": kind, "geometry": case.geometry}
    sl, T_true, in_env = hunt.build_case(case, geom)
    img, spacing, T_on = damage(kind, sl.pixels, sl.pixel_spacing_mm, np.random.default_rng([seed, index, 99]),
                                true_centres_rc(geom, T_true, sl.pixel_spacing_mm))
    if T_on is not None:
        T_true = invert(T_on) @ T_true
    t0 = time.perf_counter()
    out.update(hunt.solve_and_judge(Slice(img, spacing, slice_thickness_mm=sl.slice_thickness_mm,
                                          source=f"case{index}"), geom, T_true, ndigits=4))
    out.update(in_envelope=bool(in_env), wall_s=round(time.perf_counter() - t0, 3))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    with ProcessPoolExecutor(max_workers=args.workers, initializer=_init) as ex:
        results = list(ex.map(run_case, range(args.cases), [args.seed] * args.cases, chunksize=5))
    counts = collections.defaultdict(collections.Counter)
    for r in results:
        counts[r["kind"]][r["outcome"]] += 1
    print(f"{'damage':>16} {'cases':>6} {'ok':>5} {'false':>6} {'no_lock':>8} {'crash':>6}")
    for kind in KINDS:
        c = counts[kind]
        print(f"{kind:>16} {sum(c.values()):>6} {c['ok']:>5} {c['false_lock']:>6} {c['no_lock']:>8} {c['crash']:>6}")
    total = collections.Counter(r["outcome"] for r in results)
    print(f"cases {len(results)}: ok {total['ok']}, FALSE LOCKS {total['false_lock']}, no_lock {total['no_lock']}, "
          f"crashes {total['crash']}")
    for r in results:
        if r["outcome"] in ("false_lock", "crash") or r["wall_s"] > SLOW_S:
            print({k: v for k, v in r.items() if k != "trace"})
    print(f"wall {time.perf_counter() - t0:.0f} s, {args.workers} workers; load average {load0:.2f} at start, "
          f"{os.getloadavg()[0]:.2f} at end; seed {args.seed}")
    return 1 if total["crash"] else 0


if __name__ == "__main__":
    sys.exit(main())
