"""False-lock hunt: random slices over and beyond the usable envelope, damaged, solved, checked against the truth.

    .venv/bin/python benchmarks/hunt.py [--cases 5000] [--seed 0] [--workers 2] [--geometry G.yaml ...]

Every case is a simulated slice of one of the geometries (default: the neuro
and needle-guide exports, or the same geometries built from ``designs/`` when
they are not exported) at a random pose (depth from -15 % to 115 % of the body
length, tilt 0-80 deg, any azimuth and twist, random pixel size, field of
view, slice thickness, centre offset and Rician SNR), with one damage kind
(``MUTATIONS``; the cases, their damage and the judging are
:mod:`chic_register.studies.damage`'s). It is solved with :func:`chic_register.pipeline.register.register` as
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
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from dataclasses import asdict  # noqa: E402
from pathlib import Path  # noqa: E402

from chic_register.studies import damage  # noqa: E402
from chic_register.studies.damage import MUTATIONS, REFUSE_EXPECTED, Case, make_case  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DESIGNS = {"neuro": ROOT / "designs" / "neuro.yaml", "needle-guide": ROOT / "designs" / "needle-guide.yaml"}


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


def run_case(case: Case, geometries: dict | None = None, options: dict | None = None) -> dict:
    """Solve one case (:func:`chic_register.studies.damage.run_case`) with ``geometries``, default the worker's, and
    ``options`` (fields of :class:`~chic_register.options.SolveOptions`)."""
    return damage.run_case(case, geometries or _GEOMS, options)


def hunt(n_cases: int, seed: int = 0, workers: int = 2, paths=None, start: int = 0,
         blob_width=(1.0, 1.0), options: dict | None = None) -> list[dict]:
    """Run cases ``start .. start + n_cases - 1``; one result dict per case, in order."""
    geoms = load_geometries(paths)
    cases = [make_case(i, seed, geoms, blob_width) for i in range(start, start + n_cases)]
    if workers <= 1:
        return [run_case(c, geoms, options) for c in cases]
    with ProcessPoolExecutor(max_workers=workers, initializer=_init, initargs=(paths,)) as ex:
        return list(ex.map(run_case, cases, [None] * len(cases), [options] * len(cases), chunksize=8))


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
    ap.add_argument("--scale-sd", type=float, default=None, metavar="PCT",
                    help="solve as chic-register solve --scale-sd PCT (an unmeasured in-plane scale of that SD)")
    args = ap.parse_args(argv)
    options = None if args.scale_sd is None else {"scale_sd": args.scale_sd / 100.0}
    if args.case is not None:
        geoms = load_geometries(args.geometry)
        case = make_case(args.case, args.seed, geoms, args.blob_width)
        print(json.dumps({"case": asdict(case), "result": run_case(case, geoms, options)}, indent=2))
        return 0
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    results = hunt(args.cases, args.seed, args.workers, args.geometry, args.start, args.blob_width, options)
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
