"""False-lock hunt: random slices over and beyond the usable envelope, damaged, solved, checked against the truth.

    .venv/bin/python benchmarks/hunt.py [--cases 5000] [--seed 0] [--workers 2] [--geometry G.yaml ...]

Every case is a simulated slice of one of the geometries (default: the neuro
and needle-guide exports, or the same geometries built from ``designs/`` when
they are not exported) at a random pose (depth from -15 % to 115 % of the body
length, tilt 0-80 deg, any azimuth and twist, random pixel size, field of
view, slice thickness, centre offset and Rician SNR), with one damage kind
(``MUTATIONS``). It is solved with :func:`chic_register.pipeline.register.register` as
``chic-register solve`` does (a plain 2-D image, its pixel spacing given) and
the outcome compared with the truth:

- **false lock**: ``ok`` with a target registration error at the frame centre
  (the point on the axis at mid-length, in scanner mm) above 0.5 mm or a
  rotation error above 0.5 deg (``FALSE_LOCK_MM``, ``FALSE_LOCK_DEG``);
- **crash**: any exception other than ``NoLock``;
- **in envelope**: the true plane passes the design's plane checks
  (:func:`chic_register.model.envelope.plane_status`: every tube crosses once,
  inside the body, no two sections merge, at the slice's pixel size and
  thickness) and every tube's crossing lies in the image; the share of those
  that lock correctly is reported per damage kind.

Cases are seeded one by one (``default_rng([seed, index])``): a case is
reproduced alone with ``--case INDEX`` (which prints its settings and the
solver's answer). Exit status 1 when there is a false lock or a crash.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DESIGNS = {"neuro": ROOT / "designs" / "neuro.yaml", "needle-guide": ROOT / "designs" / "needle-guide.yaml"}
FALSE_LOCK_MM = 0.5  # the tolerance: a pose further off than this reported as ok is a false lock
FALSE_LOCK_DEG = 0.5
MUTATIONS = ("clean", "noisy", "thick_slab", "low_snr", "tool_in_bore", "distractors", "erased_tubes",
             "circle_blobs", "zeroed_pixels", "rotated_flipped", "wrong_spacing", "ghosting", "bias_field",
             "stripes")
# damage after which no pose is right: every ok is checked against the truth all the same
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

    ``blob_width`` (lo, hi): draw every blob a factor from this range x its
    tube's width (its own random stream, so the rest of the case is the same
    as without it)."""
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


def _index_map(op, shape):
    """Affine map new pixel (row, col) -> old (row, col) of an array operation ``op``: (A (2, 2), t (2,))."""
    idx = op(np.arange(shape[0] * shape[1]).reshape(shape))
    old = [np.array(divmod(int(idx[r, c]), shape[1]), float) for r, c in ((0, 0), (1, 0), (0, 1))]
    return np.stack([old[1] - old[0], old[2] - old[0]], axis=1), old[0]


def _T_old_from_new(A, t, spacing_old, spacing_new):
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
    """``(Slice to solve, true T_scanner_from_fiducial, in_envelope)`` of a case."""
    from chic_register.imaging.render import render_tubes
    from chic_register.imaging.simulate import add_rician_noise, simulate_slice
    from chic_register.model.envelope import plane_status
    from chic_register.model.pose import invert, slice_frame
    from chic_register.model.slices import Slice
    from chic_register.model.tubes import LineTube

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
        A, t = _index_map(op, img.shape)
        img = np.ascontiguousarray(op(img))
        T_on = _T_old_from_new(A, t, px, spacing)
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


_GEOMS: dict = {}


def load_geometries(paths=None) -> dict:
    """Geometries by name: from geometry files, or built from ``designs/`` (neuro, needle-guide)."""
    from chic_register.model.geometry import load_geometry

    out = {}
    if paths:
        for p in paths:
            g = load_geometry(p)
            out[g.name] = g
        return out
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec

    for name, spec in DESIGNS.items():
        export = ROOT / "exports" / name / "geometry.yaml"
        out[name] = load_geometry(export) if export.exists() else geometry_of(load_spec(spec))
    return out


def _init(paths):
    _GEOMS.clear()
    _GEOMS.update(load_geometries(paths))


def run_case(case: Case, geometries: dict | None = None) -> dict:
    """Solve one case; its outcome (``ok`` / ``false_lock`` / ``no_lock`` / ``crash``, or ``setup_error`` when the
    case itself could not be built), errors and CPU time."""
    geoms = geometries or _GEOMS
    geom = geoms[case.geometry]
    c0 = time.process_time()
    out = {"index": case.index, "geometry": case.geometry, "mutation": case.mutation}
    try:
        sl, T_true, in_env = build_case(case, geom)
    except Exception:  # the hunt's own fault, not the solver's: reported apart
        out.update(outcome="setup_error", error=traceback.format_exc(limit=3))
        return out
    out["in_envelope"] = bool(in_env)
    out.update(solve_and_judge(sl, geom, T_true))
    out["cpu_s"] = time.process_time() - c0
    return out


def solve_and_judge(sl, geom, T_true, ndigits: int | None = None, solve_geom=None) -> dict:
    """Register one slice (with ``solve_geom``, default ``geom``) and judge it against the truth: ``outcome``
    (``ok`` / ``false_lock``, beyond FALSE_LOCK_MM or FALSE_LOCK_DEG / ``no_lock`` with its ``reason`` / ``crash``
    with ``error`` and ``trace``) and the errors ``tre_mm``, ``rot_deg`` (rounded to ``ndigits`` when given)."""
    from chic_register.errors import NoLock
    from chic_register.pipeline.register import register

    try:
        reg = register([sl], solve_geom or geom)
    except NoLock as exc:
        return {"outcome": "no_lock", "reason": exc.reason}
    except Exception as exc:  # noqa: BLE001 - every other exception is a crash to report
        return {"outcome": "crash", "error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc(limit=4)}
    tre, rot = pose_error(reg.T_scanner_from_fiducial, T_true, geom.body.length)
    false = tre > FALSE_LOCK_MM or rot > FALSE_LOCK_DEG
    if ndigits is not None:
        tre, rot = round(tre, ndigits), round(rot, ndigits)
    return {"outcome": "false_lock" if false else "ok", "tre_mm": tre, "rot_deg": rot}


def hunt(n_cases: int, seed: int = 0, workers: int = 2, paths=None, start: int = 0,
         blob_width=(1.0, 1.0)) -> list[dict]:
    """Run cases ``start .. start + n_cases - 1``; one result dict per case, in order."""
    geoms = load_geometries(paths)
    cases = [make_case(i, seed, geoms, blob_width) for i in range(start, start + n_cases)]
    if workers <= 1:
        return [run_case(c, geoms) for c in cases]
    with ProcessPoolExecutor(max_workers=workers, initializer=_init, initargs=(paths,)) as ex:
        return list(ex.map(run_case, cases, chunksize=8))


def summarise(results: list[dict]) -> dict:
    """Counts over all cases and per damage kind, with the in-envelope lock share."""
    def block(rs):
        inside = [r for r in rs if r.get("in_envelope")]
        locked_in = [r for r in inside if r["outcome"] == "ok"]
        return {
            "cases": len(rs),
            "ok": sum(r["outcome"] == "ok" for r in rs),
            "false_locks": sum(r["outcome"] == "false_lock" for r in rs),
            "no_lock": sum(r["outcome"] == "no_lock" for r in rs),
            "crashes": sum(r["outcome"] == "crash" for r in rs),
            "setup_errors": sum(r["outcome"] == "setup_error" for r in rs),
            "in_envelope": len(inside),
            "in_envelope_locked": len(locked_in),
            "in_envelope_share": round(len(locked_in) / len(inside), 4) if inside else None,
        }

    per = {m: block([r for r in results if r["mutation"] == m]) for m in MUTATIONS}
    tre = [r["tre_mm"] for r in results if r["outcome"] == "ok"]
    rot = [r["rot_deg"] for r in results if r["outcome"] == "ok"]
    benign = [r for r in results if r["mutation"] not in REFUSE_EXPECTED]
    return {
        "all": block(results),
        "all_but_refuse_expected": block(benign),
        "per_mutation": per,
        "max_tre_mm_of_locks": round(max(tre), 4) if tre else None,
        "max_rot_deg_of_locks": round(max(rot), 4) if rot else None,
        "cpu_s": round(sum(r.get("cpu_s", 0.0) for r in results), 1),
    }


def format_summary(s: dict) -> str:
    a = s["all"]
    lines = [
        f"cases {a['cases']}: ok {a['ok']}, FALSE LOCKS {a['false_locks']}, no_lock {a['no_lock']}, "
        f"crashes {a['crashes']}, setup errors {a['setup_errors']}",
        f"in envelope: {a['in_envelope']} cases, {a['in_envelope_locked']} locked correctly "
        f"(share {a['in_envelope_share']}); without {', '.join(REFUSE_EXPECTED)}: "
        f"share {s['all_but_refuse_expected']['in_envelope_share']}",
        f"largest error of a correct lock: {s['max_tre_mm_of_locks']} mm, {s['max_rot_deg_of_locks']} deg",
        f"{'damage':>16} {'cases':>6} {'ok':>5} {'false':>6} {'no_lock':>8} {'crash':>6} {'in_env':>7} "
        f"{'locked':>7} {'share':>6}",
    ]
    for m, b in s["per_mutation"].items():
        share = "-" if b["in_envelope_share"] is None else f"{b['in_envelope_share']:.3f}"
        lines.append(f"{m:>16} {b['cases']:>6} {b['ok']:>5} {b['false_locks']:>6} {b['no_lock']:>8} "
                     f"{b['crashes']:>6} {b['in_envelope']:>7} {b['in_envelope_locked']:>7} {share:>6}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=500)
    ap.add_argument("--start", type=int, default=0, help="index of the first case (default 0)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--geometry", nargs="+", metavar="G", help="geometry files (default: neuro and needle-guide)")
    ap.add_argument("--case", type=int, metavar="INDEX", help="run one case and print it in full")
    ap.add_argument("--json", metavar="FILE", help="also write every case's result to FILE")
    ap.add_argument("--blob-width", nargs=2, type=float, default=(1.0, 1.0), metavar=("LO", "HI"),
                    help="draw every blob LO-HI x its tube's width, as real images do (default 1 1: as drawn)")
    args = ap.parse_args(argv)
    if args.case is not None:
        geoms = load_geometries(args.geometry)
        case = make_case(args.case, args.seed, geoms, args.blob_width)
        print(json.dumps({"case": asdict(case), "result": run_case(case, geoms)}, indent=2))
        return 0
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    results = hunt(args.cases, args.seed, args.workers, args.geometry, args.start, args.blob_width)
    wall = time.perf_counter() - t0
    s = summarise(results)
    print(format_summary(s))
    for r in results:
        if r["outcome"] in ("false_lock", "crash", "setup_error"):
            print(json.dumps({k: v for k, v in r.items() if k != "trace"}))
    print(f"wall {wall:.0f} s, CPU {s['cpu_s']:.0f} s in the solver workers (+{time.process_time() - c0:.0f} s "
          f"parent), {args.workers} workers; load average {load0:.2f} at start, {os.getloadavg()[0]:.2f} at end "
          f"on {os.cpu_count()} cores; seed {args.seed}, cases {args.start}..{args.start + args.cases - 1}")
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": s, "results": results}, indent=1))
    a = s["all"]
    return 1 if a["false_locks"] or a["crashes"] or a["setup_errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
