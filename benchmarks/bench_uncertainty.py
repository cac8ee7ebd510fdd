"""Calibration of every pose's covariance, and the cost of computing it.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_uncertainty.py [--draws 50] [--seeds 21 5 11] [--snr 20]

For ``designs/neuro.yaml`` and 3D Slicer's z001 Z-frame (the full solver,
``register``; the Z-frame with the true pose as its orientation prior, which
resolves its half-turn symmetry) at four poses each, ``--draws`` Rician slices
per pose and seed: the mean squared Mahalanobis length of the pose error
under the reported covariance (6 when calibrated), and predicted over
measured RMS TRE at the default target (1 when calibrated). Then the CPU
time of ``register`` with and without the uncertainty step on one slice.
Prints the load average: timings on a shared machine are not idle timings.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from chic_design.families import geometry_of  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402
from chic_register.imaging.simulate import simulate_slice  # noqa: E402
from chic_register.pipeline.register import register  # noqa: E402
from chic_register.studies.calibration import run_calibration, z001_geometry  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CHIC_POSES = [(35.0, 25.0, 300.0, 20.0), (22.0, 15.0, 30.0, 10.0), (30.0, 30.0, 100.0, 40.0), (15.0, 20.0, 200.0, 5.0)]
Z_POSES = [(30.0, 0.0, 0.0, 0.0), (25.0, 10.0, 30.0, 10.0), (35.0, 20.0, 100.0, 40.0), (20.0, 15.0, 200.0, 5.0)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=50, help="draws per pose and seed (default 50)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[21, 5, 11])
    ap.add_argument("--snr", type=float, default=20.0)
    args = ap.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f} (2 cores shared)")
    neuro = geometry_of(load_spec(ROOT / "designs" / "neuro.yaml"))
    for name, geom, poses, prior in (("neuro", neuro, CHIC_POSES, False),
                                     ("zframe-z001", z001_geometry(), Z_POSES, True)):
        all_m2, ratios = [], []
        for seed in args.seeds:
            c0 = time.process_time()
            cal = run_calibration(geom, poses, args.draws, seed, snr=args.snr, prior=prior)
            all_m2.append(cal.mahalanobis2)
            ratios.append(cal.tre_ratio)
            print(f"{name:12s} seed {seed:3d}: {cal.mahalanobis2.size} draws ({cal.n_no_lock} no-lock), "
                  f"Mahalanobis^2 mean {cal.mahalanobis_mean:.2f} (6 when calibrated), predicted/measured TRE "
                  f"{cal.tre_ratio:.3f}; CPU {time.process_time() - c0:.1f} s")
        m2 = np.concatenate(all_m2)
        print(f"{name:12s} all seeds: Mahalanobis^2 mean {m2.mean():.2f} +- {m2.std() / np.sqrt(m2.size):.2f} "
              f"over {m2.size} draws; TRE ratio per seed {', '.join(f'{r:.3f}' for r in ratios)}")
    sim = simulate_slice(neuro, 22.0, 15.0, 30.0, 10.0, noise="rician", snr=args.snr, rng=1)
    for flag in (True, False):
        register([sim.slice], neuro, uncertainty=flag)
        c0 = time.process_time()
        n = 40
        for _ in range(n):
            reg = register([sim.slice], neuro, uncertainty=flag)
        cpu = (time.process_time() - c0) / n * 1e3
        print(f"register with uncertainty={flag}: {cpu:.2f} ms CPU per slice"
              + (f" (uncertainty step {reg.timing_ms['uncertainty']:.2f} ms wall)" if flag else ""))
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
