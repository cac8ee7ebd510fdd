"""False-lock hunt on damage the main hunt does not draw: what a real scanner or a pipeline may do to a slice.

    .venv/bin/python benchmarks/hunt_unlisted.py [--cases 1000] [--seed 7] [--workers 2]

Each case is one of ``benchmarks/hunt.py``'s random slices (its ``noisy``
variant: Rician noise, no other damage), then one of :data:`KINDS` applied
(case ``i`` gets kind ``i % len(KINDS)``): bright specks (hot pixels), motion
blur along rows or columns, Gibbs ringing (k-space cut to 25-60 % along one
axis), a fold-over (wrap-around) strip, quantisation to 4-15 levels, a 2x
bilinear zoom declared with half the spacing (a scanner's interpolated
matrix), NaN pixels, a negative offset (a background subtracted), an
anisotropic blur and a k-space spike (a stripe pattern over the whole
image). Reports per kind ok / false lock / no_lock / crash (as hunt.py: a
false lock is ``ok`` more than 0.5 mm or 0.5 deg from the truth) and lists
the false locks, crashes and cases over 8 s of wall time. Each worker is
limited to 3 GiB of address space, so a runaway allocation is a crash here.
Exit status 1 on a crash.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import collections  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import hunt  # noqa: E402

KINDS = ("specks", "motion_blur", "gibbs", "wrap", "quantize", "zoom2", "nan_pixels", "offset_negative",
         "aniso_blur", "spike_kspace")
MEMORY_LIMIT_BYTES = 3 * 2**30
SLOW_S = 8.0


def damage(kind: str, img: np.ndarray, spacing, rng: np.random.Generator):
    """``(pixels, pixel spacing)`` of a slice after one damage ``kind`` (see the module docstring)."""
    from scipy import ndimage as ndi

    img = np.array(img, float)
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
    return img, spacing


def _init() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))
    hunt._init(None)


def run_case(index: int, seed: int) -> dict:
    """One case: its damage kind, outcome, errors and wall time."""
    from chic_register.errors import NoLock
    from chic_register.slices import Slice
    from chic_register.solve import register

    geoms = hunt._GEOMS
    case = dataclasses.replace(hunt.make_case(index, seed, geoms), mutation="noisy")
    geom = geoms[case.geometry]
    kind = KINDS[index % len(KINDS)]
    out = {"index": index, "kind": kind, "geometry": case.geometry}
    sl, T_true, in_env = hunt.build_case(case, geom)
    img, spacing = damage(kind, sl.pixels, sl.pixel_spacing_mm, np.random.default_rng([seed, index, 99]))
    t0 = time.perf_counter()
    try:
        reg = register([Slice(img, spacing, slice_thickness_mm=sl.slice_thickness_mm, source=f"case{index}")], geom)
    except NoLock as exc:
        out.update(outcome="no_lock", reason=exc.reason)
    except Exception as exc:  # noqa: BLE001 - every other exception is a crash to report
        out.update(outcome="crash", error=f"{type(exc).__name__}: {exc}", trace=traceback.format_exc(limit=4))
    else:
        tre, rot = hunt.pose_error(reg.T_scanner_from_fiducial, T_true, geom.body.length)
        false = tre > hunt.FALSE_LOCK_MM or rot > hunt.FALSE_LOCK_DEG
        out.update(outcome="false_lock" if false else "ok", tre_mm=round(tre, 4), rot_deg=round(rot, 4))
    out.update(in_envelope=bool(in_env), wall_s=round(time.perf_counter() - t0, 3))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
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
