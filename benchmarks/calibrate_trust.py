"""Calibrate the optimiser's "the solver will trust it" factor: the solver's own 1-sigma estimate over the CRLB.

The solver refuses a pose whose predicted 3-sigma error (``verify_pose.pose_precision``: the residual scatter
at its 90 % chi-square upper bound through the crossings' Jacobian) exceeds ``SolveOptions.trust_tre_mm`` at
the frame centre or ``trust_rot_deg``. The optimiser predicts that estimate from the Cramér-Rao bound of the
pose (``chic_register.precision.crlb``, worst direction, :mod:`chic_design.optimize.trust`) times a factor. This script
measures the ratio: for each design and pose it simulates ``--draws`` noisy slice sets (Rician, the protocol's
pixel, thickness and SNR; ``n`` parallel slices one thickness apart), registers them with the trust limits at
0 (so every pose that passes the other checks is refused by the precision test, which reports its sigmas),
and divides by the bound's worst-direction SDs at that pose.

    python benchmarks/calibrate_trust.py --draws 6 --seed 0
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: (name, spec, pixel mm, thickness mm, depths mm, tilts deg): the two example requirements' protocols.
CASES = (
    ("neuro", ROOT / "designs" / "neuro.yaml", 0.5, 2.0, (12.0, 24.0, 36.0), (0.0, 20.0)),
    ("needle-guide-p01", ROOT / "benchmarks" / "data" / "needle-guide-p01.yaml", 0.3, 1.5, (10.0, 17.5, 25.0),
     (0.0, 15.0)),
)


def main(argv=None) -> int:
    from chic_design.families import geometry_of
    from chic_design.optimize.confirm import simulate_parallel
    from chic_design.optimize.trust import solver_sds
    from chic_design.spec import load_spec
    from chic_register.errors import ImprecisePose, NoLock
    from chic_register.pipeline.register import register
    from chic_register.precision.crlb import Protocol, pose_crlb

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--draws", type=int, default=6)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--snr", type=float, default=20.0)
    p.add_argument("--n-slices", type=int, nargs="+", default=[1, 3])
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    all_rot, all_tre = [], []
    print(f"{'design':<17} {'n':>2} {'depth':>5} {'tilt':>4} {'az':>3} {'crlb rot':>8} {'crlb tre':>8} "
          f"{'locks':>5} {'rot ratio med/max':>17} {'tre ratio med/max':>17}")
    for name, spec_path, px, thick, depths, tilts in CASES:
        geom = geometry_of(load_spec(spec_path))
        for n in args.n_slices:
            proto = Protocol(pixel_size_mm=px, slice_thickness_mm=thick, snr=args.snr, n_slices=n,
                             slice_spacing_mm=thick)
            for z in depths:
                for t in tilts:
                    for az in ((0.0, 90.0) if t > 0 else (0.0,)):
                        b = pose_crlb(geom, z, t, az, 0.0, proto, quality="fast")
                        c_tre, c_rot = solver_sds(b.covariance, geom.body.length)
                        rr, tr = [], []
                        for _ in range(args.draws):
                            sims = simulate_parallel(geom, z, t, az, 0.0, n, thick, px, thick, args.snr, rng)
                            try:
                                register([s.slice for s in sims], geom, trust_tre_mm=0.0, trust_rot_deg=0.0)
                            except ImprecisePose as exc:
                                rr.append(exc.detail["sigma_rot_deg"] / c_rot)
                                tr.append(exc.detail["sigma_tre_mm"] / c_tre)
                            except NoLock:
                                pass
                        all_rot += rr
                        all_tre += tr
                        f = (lambda v: f"{np.median(v):7.2f} / {np.max(v):6.2f}" if v else f"{'-':>17}")  # noqa: E731
                        print(f"{name:<17} {n:>2} {z:>5g} {t:>4g} {az:>3g} {c_rot:>8.3f} {c_tre:>8.3f} "
                              f"{len(rr):>2}/{args.draws:<2} {f(rr):>17} {f(tr):>17}", flush=True)
    q = [0, 50, 90, 95, 100]
    print(f"all locks ({len(all_rot)}): rotation ratio percentiles {q}: "
          f"{np.round(np.percentile(all_rot, q), 2).tolist()}; TRE ratio: {np.round(np.percentile(all_tre, q), 2).tolist()}")
    print(f"wall {time.perf_counter() - t_wall:.0f} s, CPU {time.process_time() - t_cpu:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
