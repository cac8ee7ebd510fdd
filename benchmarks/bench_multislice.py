"""How precision improves with 1, 2 and 3 slices registered jointly.

Many noisy draws of a parallel stack of three slices through the fiducial at
one fixed pose (same tilt, azimuth and twist; depths ``d - gap``, ``d``,
``d + gap``). Each draw is registered from the middle slice alone, from the
middle and the next one, and from all three. Errors are those of the middle
slice's pose in the fiducial frame F (x, y, z of the true axis crossing
under the estimated registration, tilt and twist; see
:func:`chic_register.studies.reslice.slice_errors`), so the three rows measure the
same quantity. Prints the mean, SD and RMS per axis, and the no-lock count.

    .venv/bin/python benchmarks/bench_multislice.py --draws 200 --snr 10
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chic_design.families import geometry_of  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402
from chic_register.errors import NoLock  # noqa: E402
from chic_register.imaging.simulate import simulate_slice  # noqa: E402
from chic_register.model.pose import rigid, rot_y, rot_z, slice_angles, slice_frame  # noqa: E402
from chic_register.pipeline.register import register  # noqa: E402
from chic_register.studies.reslice import AXES, slice_errors  # noqa: E402

SUBSETS = {1: (1,), 2: (1, 2), 3: (0, 1, 2)}  # indices into the stack (0: shallow, 1: middle, 2: deep)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", default=str(ROOT / "designs" / "neuro.yaml"))
    p.add_argument("--draws", type=int, default=100)
    p.add_argument("--depth", type=float, default=25.0, help="middle slice depth (mm)")
    p.add_argument("--gap", type=float, default=5.0, help="depth step between slices (mm)")
    p.add_argument("--tilt", type=float, default=10.0)
    p.add_argument("--azimuth", type=float, default=30.0)
    p.add_argument("--twist", type=float, default=20.0)
    p.add_argument("--noise", default="rician", choices=["uniform", "rician"])
    p.add_argument("--snr", type=float, default=10.0, help="Rician SNR of fluid")
    p.add_argument("--noise-level", type=float, default=0.5, help="uniform noise amplitude (fluid = 1)")
    p.add_argument("--thickness", type=float, default=2.0, help="slice thickness (mm)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = p.parse_args(argv)

    geom = geometry_of(load_spec(args.design))
    T_true = rigid(rot_z(35.0) @ rot_y(20.0), (12.0, -30.0, 55.0))  # the fiducial in the scanner
    depths = [args.depth - args.gap, args.depth, args.depth + args.gap]
    frames = [slice_frame(d, args.tilt, args.azimuth, args.twist) for d in depths]
    rng = np.random.default_rng(args.seed)
    errors = {n: [] for n in SUBSETS}
    no_lock = {n: 0 for n in SUBSETS}
    solve_ms = {n: [] for n in SUBSETS}
    t_start = time.perf_counter()
    for _ in range(args.draws):
        stack = [
            simulate_slice(geom, d, args.tilt, args.azimuth, args.twist, T_scanner_from_fiducial=T_true,
                           slice_thickness_mm=args.thickness, noise=args.noise, snr=args.snr,
                           noise_level=args.noise_level, rng=rng)
            for d in depths
        ]
        T_scanner_from_S = T_true @ frames[1]
        for n, idx in SUBSETS.items():
            t0 = time.perf_counter()
            try:
                reg = register([stack[i].slice for i in idx], geom)
            except NoLock:
                no_lock[n] += 1
                continue
            solve_ms[n].append(1000.0 * (time.perf_counter() - t0))
            e = slice_errors(reg.T_scanner_from_fiducial, T_scanner_from_S, slice_angles(frames[1]))
            errors[n].append([e[a] for a in AXES])
    elapsed = time.perf_counter() - t_start

    print(f"{geom.name}: {args.draws} draws, stack depths {depths} mm, tilt {args.tilt:g}, azimuth "
          f"{args.azimuth:g}, twist {args.twist:g} deg, {args.thickness:g} mm slices, noise {args.noise} "
          f"({'SNR %g' % args.snr if args.noise == 'rician' else 'amplitude %g' % args.noise_level}), "
          f"seed {args.seed}; {elapsed:.1f} s")
    head = f"{'slices':>6s} {'locked':>7s}  " + "  ".join(f"{a:>16s}" for a in AXES) + "  solve ms"
    print("SD (RMS) of the middle slice's pose error")
    print(head)
    result = {"settings": vars(args), "depths_mm": depths, "rows": {}}
    for n in SUBSETS:
        e = np.array(errors[n]).reshape(-1, len(AXES))
        sd = e.std(axis=0, ddof=1) if len(e) > 1 else np.full(len(AXES), np.nan)
        rms = np.sqrt((e**2).mean(axis=0)) if len(e) else np.full(len(AXES), np.nan)
        mean = e.mean(axis=0) if len(e) else np.full(len(AXES), np.nan)
        ms = float(np.median(solve_ms[n])) if solve_ms[n] else float("nan")
        cells = "  ".join(f"{s:7.4f} ({r:6.4f})" for s, r in zip(sd, rms))
        print(f"{n:6d} {len(e):4d}/{args.draws:<3d} {cells}  {ms:7.1f}")
        result["rows"][n] = {"locked": len(e), "no_lock": no_lock[n], "median_solve_ms": ms,
                             **{a: {"sd": float(sd[i]), "rms": float(rms[i]), "mean": float(mean[i])}
                                for i, a in enumerate(AXES)}}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
