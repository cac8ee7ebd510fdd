"""Speed of detection + pose on 256 x 256 slices, on one core.

    OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_solve.py [--repeats 20]

Simulates a spread of poses of designs/neuro.yaml (uniform noise 0.1, 2 mm
slices), then times ``register([slice], geom)`` repeatedly (after one warm-up
call per slice) and reports the median and 95th percentile of the total,
detect and pose times. Thread pools are pinned to one thread.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from chic_design.layout import fiducial_geometry  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402
from chic_register.simulate import simulate_slice  # noqa: E402
from chic_register.solve import register  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--design", default=str(ROOT / "designs" / "neuro.yaml"))
    args = ap.parse_args()
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass
    geom = fiducial_geometry(load_spec(args.design))
    L = geom.body.length
    rng = np.random.default_rng(0)
    poses = [(f * L, t, a, w) for f in (0.2, 0.5, 0.8) for t in (0, 20, 40) for a, w in ((0, 0), (130, 45))]
    slices = [simulate_slice(geom, *p, noise="uniform", noise_level=0.1, rng=rng).slice for p in poses]
    for sl in slices:
        register([sl], geom)  # warm-up
    total, det, pose = [], [], []
    for _ in range(args.repeats):
        for sl in slices:
            t0 = time.perf_counter()
            r = register([sl], geom)
            total.append((time.perf_counter() - t0) * 1e3)
            det.append(r.timing_ms["detect"])
            pose.append(r.timing_ms["pose"])
    for name, v in (("total (wall)", total), ("detect", det), ("pose", pose)):
        v = np.asarray(v)
        print(f"{name:>13}: median {np.median(v):6.2f} ms, p95 {np.percentile(v, 95):6.2f} ms, "
              f"min {v.min():6.2f} ms  ({v.size} solves of {len(slices)} slices)")
    print(f"target: median total < 5 ms -> {'met' if np.median(total) < 5 else 'MISSED'}; load average "
          f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
