"""Equality set: every solver outcome on a fixed set of slices, written as JSON, to prove a change alters nothing.

    .venv/bin/python benchmarks/equality.py --out before.json [--cases 1000] [--workers 2]
    .venv/bin/python benchmarks/equality.py --compare before.json after.json

The set is the bench slices (``bench_solve.py``'s 18 poses of ``designs/neuro.yaml``) and the first ``--cases``
cases of the false-lock hunt (seed 0), each solved with verification on and off. Per solve it records the
outcome (``ok``: the whole JSON object but the timing; ``no_lock``: the reason and its detail; ``crash``: the
error), the pose to 1e-9. ``--compare`` prints every case that differs and exits 1 when any does.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import hunt  # noqa: E402

from chic_register.studies.damage import build_case, make_case  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _register():
    from chic_register import NoLock, register
    return register, NoLock


def _rounded(obj):
    if isinstance(obj, float):
        return round(obj, 9)
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items() if k != "timing_ms"}
    if isinstance(obj, (list, tuple)):
        return [_rounded(v) for v in obj]
    if isinstance(obj, np.generic):
        return _rounded(obj.item())
    return obj


def solve_record(sl, geom, verify: bool) -> dict:
    register, NoLock = _register()
    try:
        reg = register([sl], geom, verify=verify)
    except NoLock as exc:
        return {"outcome": "no_lock", "reason": exc.reason, "detail": _rounded(dict(exc.detail or {}))}
    except Exception as exc:  # noqa: BLE001 - recorded as a crash
        return {"outcome": "crash", "error": f"{type(exc).__name__}: {exc}"}
    return {"outcome": "ok", **_rounded(reg.to_dict())}


def _hunt_case(index: int) -> dict:
    geoms = hunt._GEOMS
    case = make_case(index, 0, geoms)
    sl, _, _ = build_case(case, geoms[case.geometry])
    geom = geoms[case.geometry]
    return {"key": f"hunt{index}", "on": solve_record(sl, geom, True), "off": solve_record(sl, geom, False)}


def bench_records() -> list[dict]:
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec
    from chic_register.imaging.simulate import simulate_slice

    geom = geometry_of(load_spec(ROOT / "designs" / "neuro.yaml"))
    L = geom.body.length
    rng = np.random.default_rng(0)
    poses = [(f * L, t, a, w) for f in (0.2, 0.5, 0.8) for t in (0, 20, 40) for a, w in ((0, 0), (130, 45))]
    out = []
    for k, p in enumerate(poses):
        sl = simulate_slice(geom, *p, slice_thickness_mm=2.0, noise="rician", snr=20.0, rng=rng).slice
        out.append({"key": f"bench{k}", "on": solve_record(sl, geom, True), "off": solve_record(sl, geom, False)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="write the set's outcomes to this JSON file")
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"))
    args = ap.parse_args(argv)
    if args.compare:
        a, b = (json.loads(Path(p).read_text()) for p in args.compare)
        diff = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
        for k in diff:
            print(f"{k}:\n  {json.dumps(a.get(k))[:600]}\n  {json.dumps(b.get(k))[:600]}")
        print(f"{len(diff)} of {len(set(a) | set(b))} records differ")
        return 1 if diff else 0
    if not args.out:
        ap.error("give --out FILE or --compare A B")
    recs = bench_records()
    with ProcessPoolExecutor(max_workers=args.workers, initializer=hunt._init, initargs=(None,)) as ex:
        recs += list(ex.map(_hunt_case, range(args.cases), chunksize=8))
    Path(args.out).write_text(json.dumps({r["key"]: {"on": r["on"], "off": r["off"]} for r in recs}, indent=0))
    ok = sum(r["on"]["outcome"] == "ok" for r in recs)
    print(f"wrote {args.out}: {len(recs)} slices, {ok} ok with verification on")
    return 0


if __name__ == "__main__":
    sys.exit(main())
