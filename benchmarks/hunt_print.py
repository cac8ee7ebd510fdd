"""False-lock hunt on what a print and its geometry file get wrong: the fiducial differs from the file, not the image.

    .venv/bin/python benchmarks/hunt_print.py --kind KIND [--cases 300] [--seed 5] [--workers 2] [--amount X]
        [--scale-sd PCT]

Each case is one of ``benchmarks/hunt.py``'s random slices (its ``noisy``
variant: Rician noise, no other damage), changed by one ``KIND``:

- ``bubble``: one or two sections partly dark (air in the channel: the part
  beyond a chord 0.5 radii before to 0.8 radii past the centre, background noise);
- ``water_bath``: water at 20-100 % of the fluid's level outside the body, in
  its bore and beyond its end faces (a fiducial scanned in a bath);
- ``dim_tube``: one tube at 20-60 % of the others' signal (a weaker fill);
- ``scale``: the pixel spacing declared ``--amount`` (a fraction, default
  0.002) too large along both axes about the fiducial's centre, which is
  what a print that much too large looks like (a gradient calibration off
  by as much scales about the isocentre: ``hunt_distortion.py``);
- ``helix_offset``: solved with a geometry file built from the same design
  with ``helix.offset_deg`` ``--amount`` degrees larger (default 0.5): a stale
  file after a design change, or helices printed turned against the straight
  tubes;
- ``other_design``: solved with the other design's geometry file (neuro's
  slices with the needle guide's, and the reverse).

The damage is :func:`chic_register.studies.damage.print_damage`'s. ``--scale-sd PCT``
solves as ``chic-register solve --scale-sd PCT`` does: the single slice's
covariance and trust test then hold an unmeasured scale of that SD. Reports
ok / false lock (more than 0.5 mm or 0.5 deg from the truth, as hunt.py) /
no_lock / crash, and lists the false locks. Exit status 1 on a crash.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import collections  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import hunt  # noqa: E402

from chic_register.studies.damage import (  # noqa: E402
    PRINT_DEFAULT_AMOUNT,
    PRINT_KINDS,
    other_design_geometries,
    run_print_case,
)

KINDS = PRINT_KINDS
DEFAULT_AMOUNT = PRINT_DEFAULT_AMOUNT


def offset_geometry(name: str, change_deg: float):
    """The geometry of design ``name`` (``designs/<name>.yaml``) with its helix offset ``change_deg`` larger."""
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec

    spec = load_spec(hunt.DESIGNS[name])
    d = spec.model_dump()
    d["helix"]["offset_deg"] += change_deg
    return geometry_of(type(spec).model_validate(d))


_WRONG: dict = {}


def _init(kind: str, amount: float) -> None:
    hunt._init(None)
    _WRONG.clear()
    if kind == "helix_offset":
        _WRONG.update({name: offset_geometry(name, amount) for name in hunt._GEOMS})
    elif kind == "other_design":
        if len(hunt._GEOMS) < 2:
            raise SystemExit("hunt_print: other_design needs two designs (hunt.DESIGNS)")
        _WRONG.update(other_design_geometries(hunt._GEOMS))


def run_case(index: int, seed: int, kind: str, amount: float, options: dict) -> dict:
    """One case (:func:`chic_register.studies.damage.run_print_case`): outcome, errors."""
    return run_print_case(index, seed, kind, amount, hunt._GEOMS, _WRONG, options)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kind", choices=KINDS, required=True)
    ap.add_argument("--cases", type=int, default=300)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--amount", type=float, default=None, help="scale: a fraction; helix_offset: degrees added")
    ap.add_argument("--scale-sd", type=float, default=None, metavar="PCT",
                    help="solve as chic-register solve --scale-sd PCT (the in-plane scale known to PCT, 1 SD per axis)")
    args = ap.parse_args(argv)
    options = {} if args.scale_sd is None else {"scale_sd": args.scale_sd / 100.0}
    amount = DEFAULT_AMOUNT.get(args.kind, 0.0) if args.amount is None else args.amount
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    n = args.cases
    with ProcessPoolExecutor(max_workers=args.workers, initializer=_init, initargs=(args.kind, amount)) as ex:
        results = list(ex.map(run_case, range(n), [args.seed] * n, [args.kind] * n, [amount] * n, [options] * n,
                              chunksize=5))
    total = collections.Counter(r["outcome"] for r in results)
    inside = collections.Counter(r["outcome"] for r in results if r["in_envelope"])
    told = "" if args.scale_sd is None else f", --scale-sd {args.scale_sd:g}"
    print(f"{args.kind} (amount {amount:g}{told}), cases {n}: ok {total['ok']}, FALSE LOCKS {total['false_lock']}, "
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
