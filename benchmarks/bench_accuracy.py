"""Accuracy on the paper's simulation protocol, against the paper and the targets (3x better than its maxima).

    .venv/bin/python benchmarks/bench_accuracy.py [--draws 20] [--levels 0.1 0.05 0.025 0.01] [--snr 20 50 | --snr]
        [--centroid-model on|off]

Runs :func:`chic_register.evaluate.run_study` on designs/neuro.yaml (256 x 256,
0.5 mm pixels, thin sections) with the paper's uniform white noise at each
amplitude of ``--levels`` (fluid = 1, noise U(-a, a)) and with Rician noise at
``--snr``, and prints each group's max |error| and std beside the paper's
figures and the target (paper max / 3).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from chic_design.layout import fiducial_geometry
from chic_design.spec import load_spec
from chic_register.evaluate import PAPER, format_summary, run_study

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--levels", type=float, nargs="+", default=[0.1, 0.05, 0.025, 0.01])
    ap.add_argument("--snr", type=float, nargs="*", default=[20.0, 50.0])
    ap.add_argument("--slice-thickness", type=float, default=0.0)
    ap.add_argument("--centroid-model", choices=("on", "off"), default="on",
                    help="solver's centroid model (default on, as the study)")
    ap.add_argument("--design", default=str(ROOT / "designs" / "neuro.yaml"))
    args = ap.parse_args()
    opts = {"centroid_model": args.centroid_model == "on"}
    geom = fiducial_geometry(load_spec(args.design))
    runs = [("uniform", a) for a in args.levels] + [("rician", s) for s in args.snr]
    for kind, value in runs:
        t0 = time.perf_counter()
        r = run_study(geom, args.draws, args.seed, noise=kind, noise_level=value if kind == "uniform" else 0.1,
                      snr=value if kind == "rician" else 20.0, slice_thickness_mm=args.slice_thickness,
                      register_options=opts)
        print(format_summary(r))
        verdict = []
        for g, v in r.summary().items():
            target = PAPER[g][0] / 3
            verdict.append(f"{g} {'met' if v['max'] <= target and v['no_lock'] == 0 else 'MISSED'} "
                           f"({v['max']:.4f} vs {target:.4f} {v['unit']})")
        print("targets (paper max / 3): " + "; ".join(verdict))
        ms = r.ms[np.isfinite(r.ms)]
        print(f"detect + pose per slice: median {np.median(ms):.1f} ms ({time.perf_counter() - t0:.0f} s)\n",
              flush=True)


if __name__ == "__main__":
    main()
