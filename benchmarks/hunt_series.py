"""False-lock hunt for series: random parallel slices (2-4) solved together, checked against the truth.

    .venv/bin/python benchmarks/hunt_series.py [--cases 300] [--seed 11]

Each case is a series of 2-4 parallel simulated slices (1-3 mm apart, 1-3 mm
thick, Rician SNR 8-40) of ``neuro``, ``needle-guide`` or the optimiser's slim
needle guide (``tests/data/needle-guide-slim.yaml``, 0.3 mm pixels; the others
0.4-0.8 mm) at a random pose (depth -10 % to 110 % of the body, tilt 0-60 deg,
any azimuth and twist), registered as one series. A pose reported ok that is
more than 0.5 mm (frame centre) or 0.5 deg off is a false lock; exit status 1
when there is one or a crash. Complements ``hunt.py`` (single damaged slices).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

DESIGNS = {"neuro": ROOT / "designs" / "neuro.yaml", "needle-guide": ROOT / "designs" / "needle-guide.yaml",
           "slim": ROOT / "tests" / "data" / "needle-guide-slim.yaml"}


def main(argv=None) -> int:
    from chic_design.families import geometry_of
    from chic_design.optimize.confirm import simulate_parallel
    from chic_design.spec import load_spec
    from chic_register.errors import NoLock
    from chic_register.pipeline.register import register
    from chic_register.studies.damage import FALSE_LOCK_DEG, FALSE_LOCK_MM, pose_error

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=300)
    ap.add_argument("--seed", type=int, default=11)
    args = ap.parse_args(argv)
    geoms = {name: geometry_of(load_spec(path)) for name, path in DESIGNS.items()}
    out, worst = Counter(), (0.0, 0.0)
    t0, c0, load0 = time.perf_counter(), time.process_time(), os.getloadavg()[0]
    for i in range(args.cases):
        rng = np.random.default_rng([args.seed, i])
        name = list(geoms)[i % len(geoms)]
        g = geoms[name]
        L = g.body.length
        depth, tilt = rng.uniform(-0.1, 1.1) * L, rng.uniform(0, 60)
        az, tw = rng.uniform(0, 360), rng.uniform(-180, 180)
        px = 0.3 if name == "slim" else rng.uniform(0.4, 0.8)
        n = int(rng.integers(2, 5))
        sims = simulate_parallel(g, depth, tilt, az, tw, n, rng.uniform(1.0, 3.0), px, rng.uniform(1, 3),
                                 rng.uniform(8, 40), rng)
        T_true = sims[0].truth.T_scanner_from_fiducial
        try:
            reg = register([s.slice for s in sims], g)
        except NoLock:
            out["no_lock"] += 1
            continue
        except Exception as exc:  # noqa: BLE001 - a crash is a finding
            out["crash"] += 1
            print(f"CRASH case {i}: {exc!r}")
            continue
        tre, rot = pose_error(reg.T_scanner_from_fiducial, T_true, L)
        if tre > FALSE_LOCK_MM or rot > FALSE_LOCK_DEG:
            out["false_lock"] += 1
            print(f"FALSE LOCK case {i}: {name}, depth {depth:.1f}, tilt {tilt:.1f}: {tre:.2f} mm, {rot:.2f} deg")
        else:
            out["ok"] += 1
            worst = (max(worst[0], tre), max(worst[1], rot))
    print(f"series {args.cases}: ok {out['ok']}, FALSE LOCKS {out['false_lock']}, no_lock {out['no_lock']}, "
          f"crashes {out['crash']}; largest error of a correct lock {worst[0]:.3f} mm, {worst[1]:.3f} deg")
    print(f"wall {time.perf_counter() - t0:.0f} s, CPU {time.process_time() - c0:.0f} s; load average {load0:.2f} "
          f"at start, {os.getloadavg()[0]:.2f} at end; seed {args.seed}")
    return 1 if out["false_lock"] or out["crash"] else 0


if __name__ == "__main__":
    sys.exit(main())
