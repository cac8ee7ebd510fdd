"""Speed of ``solve VOLUME`` without ``--slices``: every native slice tried, the locked ones registered jointly.

    OMP_NUM_THREADS=1 taskset -c 1 .venv/bin/python benchmarks/bench_volume.py [--slices 60] [--repeats 3]

Simulates a 60-slice volume (Rician SNR 20) of designs/neuro.yaml (128 x 128
x 0.5 mm, 1 mm slices, reaching past both ends of the body) and of the z001
Z-frame (built here as seven line tubes; 112 x 112 x 1 mm, 1.5 mm slices; a
prior orientation 30 degrees off, as the frame is self-symmetric), then times
:func:`chic_register.pipeline.volume.register_volume` (wall and CPU) and
reports slices used and skipped and the target error at the body's centre.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from chic_design.families import geometry_of  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402
from chic_register.imaging.simulate import simulate_volume
from chic_register.model.body import Body  # noqa: E402
from chic_register.model.geometry import FiducialGeometry  # noqa: E402
from chic_register.model.pose import apply, rigid, rot_y, rot_z  # noqa: E402
from chic_register.model.tubes import LineTube  # noqa: E402
from chic_register.pipeline.volume import register_volume  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def zframe() -> FiducialGeometry:
    a = 30.0
    rods = [("A0", (a, -a, 0), (a, -a, 60)), ("A1", (a, a, 0), (a, a, 60)), ("A2", (-a, a, 0), (-a, a, 60)),
            ("A3", (-a, -a, 0), (-a, -a, 60)), ("Z0", (a, a, 0), (a, -a, 60)), ("Z1", (-a, a, 0), (a, a, 60)),
            ("Z2", (-a, -a, 0), (-a, a, 60))]
    return FiducialGeometry("zframe", Body(60.0, 2 * a * math.sqrt(2) + 3, 2 * a - 3),
                            tuple(LineTube(i, "other", p0, p1, 3.0) for i, p0, p1 in rods))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--slices", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass
    neuro = geometry_of(load_spec(ROOT / "designs" / "neuro.yaml"))
    zf = zframe()
    R = rot_z(20) @ rot_y(8)
    cases = [
        ("neuro", neuro, rigid(R, (1.0, -1.0, -25.0)), (128, 128, args.slices), (0.5, 0.5, 1.0), {}),
        ("zframe", zf, rigid(R, (2.0, -3.0, -30.0)), (112, 112, args.slices), (1.0, 1.0, 1.5),
         {"prior": rigid(R @ rot_z(-30), (0, 0, 0))}),
    ]
    for name, geom, T, shape, spacing, opts in cases:
        sv = simulate_volume(geom, T, shape, spacing, noise="rician", snr=20, rng=1, supersample=2,
                             thickness_samples=2)
        walls, cpus = [], []
        for _ in range(args.repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            reg = register_volume(sv.volume, geom, **opts)
            walls.append((time.perf_counter() - t0) * 1e3)
            cpus.append((time.process_time() - c0) * 1e3)
        centre = np.array([0.0, 0.0, geom.body.length / 2])
        tre = float(np.linalg.norm(apply(reg.T_scanner_from_fiducial, centre) - apply(T, centre)))
        print(f"{name}: {shape[2]} slices, {len(reg.slices)} used, {len(reg.skipped)} skipped; "
              f"median wall {np.median(walls):.0f} ms, CPU {np.median(cpus):.0f} ms "
              f"({np.median(cpus) / shape[2]:.1f} ms per slice); TRE at the centre {tre:.3f} mm")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
