"""Calibration of single-slice poses with wide blobs (the pose through the blurred model), per design.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_blurred_calibration.py [--design zframe] [--cases 80] [--seed 0]

Simulated single slices of ``designs/DESIGN.yaml`` at random poses (depth 30-70 % of the body, tilt 10-30 deg, any
azimuth and twist), Rician SNR 15-30, blobs 1.5-2.5 times the channels' width, registered with the defaults (the
Z-frame with the true pose as its prior: its half-turn symmetry). Per kind of measurement the locks report (the
uncertainty's ``measurement``): how many, the mean and median squared Mahalanobis length of the pose error under
the reported covariance (6 when calibrated; :mod:`chic_register.studies.calibration`), and the RMS and largest
rotation error.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--design", default="zframe", help="a design of designs/ (default zframe)")
    ap.add_argument("--cases", type=int, default=80)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec
    from chic_register.errors import NoLock
    from chic_register.imaging.simulate import simulate_slice
    from chic_register.pipeline.register import register
    from chic_register.precision.uncertainty import mahalanobis2
    from chic_register.studies.calibration import pose_error

    geom = geometry_of(load_spec(ROOT / "designs" / f"{args.design}.yaml"))
    rng = np.random.default_rng(args.seed)
    L = geom.body.length
    by, refused = collections.defaultdict(list), 0
    for _ in range(args.cases):
        depth, tilt = rng.uniform(0.3, 0.7) * L, rng.uniform(10, 30)
        az, tw, width, snr = rng.uniform(0, 360), rng.uniform(0, 360), rng.uniform(1.5, 2.5), rng.uniform(15, 30)
        sim = simulate_slice(geom, depth, tilt, az, tw, noise="rician", snr=snr, rng=rng, blob_width=width)
        extra = {"prior": sim.truth.T_scanner_from_fiducial} if geom.family == "zframe" else {}
        try:
            reg = register([sim.slice], geom, **extra)
        except NoLock:
            refused += 1
            continue
        d = pose_error(sim.truth.T_scanner_from_fiducial, reg.T_scanner_from_fiducial)
        by[reg.uncertainty.measurement].append((mahalanobis2(d, reg.uncertainty.covariance), float(np.linalg.norm(d[:3]))))
    print(f"{args.design}: {args.cases} single slices with blobs 1.5-2.5x, {refused} refused; seed {args.seed}")
    for what, rows in sorted(by.items()):
        a = np.array(rows)
        print(f"  {what:45s} locks {len(rows):3d}: Mahalanobis^2 mean {a[:, 0].mean():5.2f} (6 when calibrated), "
              f"median {np.median(a[:, 0]):5.2f}; rotation error RMS {np.sqrt(np.mean(a[:, 1] ** 2)):.3f} deg, "
              f"largest {a[:, 1].max():.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
