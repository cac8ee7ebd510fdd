"""False-lock hunt on what a print and its geometry file get wrong: the fiducial differs from the file, not the image.

    .venv/bin/python benchmarks/hunt_print.py --kind KIND [--cases 300] [--seed 5] [--workers 2] [--amount X]

Each case is one of ``benchmarks/hunt.py``'s random slices (its ``noisy``
variant: Rician noise, no other damage), changed by one ``KIND``:

- ``bubble``: one or two sections partly dark (air in the channel: the part
  beyond a chord 0.5 radii before to 0.8 radii past the centre, background noise);
- ``water_bath``: water at 20-100 % of the fluid's level outside the body, in
  its bore and beyond its end faces (a fiducial scanned in a bath);
- ``dim_tube``: one tube at 20-60 % of the others' signal (a weaker fill);
- ``scale``: the pixel spacing declared ``--amount`` (a fraction, default
  0.002) too large along both axes, which is what a print that much too
  large looks like (or a gradient calibration off by as much);
- ``helix_offset``: solved with a geometry file built from the same design
  with ``helix.offset_deg`` ``--amount`` degrees larger (default 0.5): a stale
  file after a design change, or helices printed turned against the straight
  tubes;
- ``other_design``: solved with the other design's geometry file (neuro's
  slices with the needle guide's, and the reverse).

Reports ok / false lock (more than 0.5 mm or 0.5 deg from the truth, as
hunt.py) / no_lock / crash, and lists the false locks. Exit status 1 on a crash.
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
import traceback  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import hunt  # noqa: E402
from hunt_unlisted import true_centres_rc  # noqa: E402

KINDS = ("bubble", "water_bath", "dim_tube", "scale", "helix_offset", "other_design")
DEFAULT_AMOUNT = {"scale": 0.002, "helix_offset": 0.5}
#: A section's neighbourhood (tube radii) that a bubble or a dim fill reaches.
REACH_RADII = 2.5


def offset_geometry(name: str, change_deg: float):
    """The geometry of design ``name`` (``designs/<name>.yaml``) with its helix offset ``change_deg`` larger."""
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec

    spec = load_spec(hunt.DESIGNS[name])
    d = spec.model_dump()
    d["helix"]["offset_deg"] += change_deg
    return geometry_of(type(spec).model_validate(d))


def change(kind: str, img: np.ndarray, sl, geom, T_true: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The slice's pixels after ``kind`` (``scale``, ``helix_offset`` and ``other_design`` leave them alone)."""
    from chic_register.model.pose import invert

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


_WRONG: dict = {}


def _init(kind: str, amount: float) -> None:
    hunt._init(None)
    _WRONG.clear()
    if kind == "helix_offset":
        _WRONG.update({name: offset_geometry(name, amount) for name in hunt._GEOMS})
    elif kind == "other_design":
        names = sorted(hunt._GEOMS)
        if len(names) < 2:
            raise SystemExit("hunt_print: other_design needs two designs (hunt.DESIGNS)")
        _WRONG.update({name: hunt._GEOMS[names[(i + 1) % len(names)]] for i, name in enumerate(names)})


def run_case(index: int, seed: int, kind: str, amount: float) -> dict:
    """One case: outcome, errors."""
    from chic_register.model.slices import Slice

    case = dataclasses.replace(hunt.make_case(index, seed, hunt._GEOMS), mutation="noisy")
    geom = hunt._GEOMS[case.geometry]
    out = {"index": index, "geometry": case.geometry}
    try:
        sl, T_true, in_env = hunt.build_case(case, geom)
        img = change(kind, sl.pixels, sl, geom, T_true, np.random.default_rng([seed, index, 7]))
    except Exception:  # the hunt's own fault, not the solver's: reported apart
        out.update(outcome="setup_error", error=traceback.format_exc(limit=3), in_envelope=False)
        return out
    spacing = tuple(v * (1 + amount) for v in sl.pixel_spacing_mm) if kind == "scale" else sl.pixel_spacing_mm
    out.update(hunt.solve_and_judge(Slice(img, spacing, slice_thickness_mm=sl.slice_thickness_mm,
                                          source=f"case{index}"), geom, T_true, ndigits=4,
                                    solve_geom=_WRONG.get(case.geometry)))
    out.update(tilt_deg=round(case.tilt_deg, 1), in_envelope=bool(in_env))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=KINDS, required=True)
    ap.add_argument("--cases", type=int, default=300)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--amount", type=float, default=None, help="scale: a fraction; helix_offset: degrees added")
    args = ap.parse_args(argv)
    amount = DEFAULT_AMOUNT.get(args.kind, 0.0) if args.amount is None else args.amount
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    n = args.cases
    with ProcessPoolExecutor(max_workers=args.workers, initializer=_init, initargs=(args.kind, amount)) as ex:
        results = list(ex.map(run_case, range(n), [args.seed] * n, [args.kind] * n, [amount] * n, chunksize=5))
    total = collections.Counter(r["outcome"] for r in results)
    inside = collections.Counter(r["outcome"] for r in results if r["in_envelope"])
    print(f"{args.kind} (amount {amount:g}), cases {n}: ok {total['ok']}, FALSE LOCKS {total['false_lock']}, "
          f"no_lock {total['no_lock']}, crashes {total['crash']}, setup errors {total['setup_error']}; in the envelope {sum(inside.values())}: "
          f"ok {inside['ok']}, false {inside['false_lock']}")
    for r in results:
        if r["outcome"] in ("false_lock", "crash", "setup_error"):
            print({k: v for k, v in r.items() if k not in ("trace", "reason")})
    print(f"wall {time.perf_counter() - t0:.0f} s, {args.workers} workers; load average {load0:.2f} at start, "
          f"{os.getloadavg()[0]:.2f} at end; seed {args.seed}")
    return 1 if total["crash"] or total["setup_error"] else 0


if __name__ == "__main__":
    sys.exit(main())
