"""Systematic (noise-free) error of the solver over a sweep of poses.

    .venv/bin/python benchmarks/bench_bias.py [--thickness 0] [--centroid-model on|off]

Noise-free slices of designs/neuro.yaml (256 x 256, 0.5 mm pixels) at tilts
0..60 degrees, several depths, azimuths and twists; prints, per tilt, the
largest depth error (mm), normal-vector error (deg) and twist error (deg).
Without noise every error is a bias of the model or of the detector.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from chic_design.families import geometry_of
from chic_design.spec import load_spec
from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import invert, wrap_deg
from chic_register.pipeline.register import register
from chic_register.studies.evaluate import normal_angle_deg

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--thickness", type=float, default=0.0)
    ap.add_argument("--centroid-model", choices=("on", "off", "default"), default="default")
    ap.add_argument("--design", default=str(ROOT / "designs" / "neuro.yaml"))
    args = ap.parse_args()
    geom = geometry_of(load_spec(args.design))
    L = geom.body.length
    kw = {} if args.centroid_model == "default" else {"centroid_model": args.centroid_model == "on"}
    print(f"{'tilt':>5} {'n':>3} {'nolock':>6} {'depth mm':>9} {'normal deg':>10} {'twist deg':>9}")
    worst = np.zeros(3)
    for tilt in (0, 15, 30, 45, 60):
        errs, nolock = [], 0
        for f in (0.2, 0.35, 0.5, 0.65, 0.8):
            for az, tw in ((0, 0), (75, 20), (160, -35), (250, 60)):
                sim = simulate_slice(geom, f * L, tilt, az, tw, slice_thickness_mm=args.thickness)
                try:
                    reg = register([sim.slice], geom, **kw)
                except NoLock:
                    nolock += 1
                    continue
                s, t = reg.slices[0], sim.truth.angles
                T_fi = invert(reg.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
                T_true = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
                errs.append((abs(s.depth_mm - t.depth_mm), normal_angle_deg(T_fi, T_true),
                             abs(wrap_deg(s.twist_deg - t.twist_deg))))
        e = np.max(errs, axis=0) if errs else np.full(3, np.nan)
        worst = np.fmax(worst, e)
        print(f"{tilt:>5} {len(errs):>3} {nolock:>6} {e[0]:>9.4f} {e[1]:>10.4f} {e[2]:>9.4f}")
    print(f"{'all':>5} {'':>3} {'':>6} {worst[0]:>9.4f} {worst[1]:>10.4f} {worst[2]:>9.4f}")


if __name__ == "__main__":
    main()
