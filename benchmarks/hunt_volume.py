"""False-lock hunt for volumes with wide blobs: random poses of ``neuro`` and ``needle-guide``, registered whole.

    .venv/bin/python benchmarks/hunt_volume.py [--cases 40] [--seed 3] [--blob-width 1.5 2.5]

Each case is a simulated 128 x 128 x 40 volume (neuro 0.5 x 0.5 x 2 mm, the needle guide 0.3 x 0.3 x 1 mm; Rician SNR
12-30) of one design at a random pose (tilt 0-30 deg, any azimuth and twist, the body's centre up to 4 mm off the
volume's centre in each direction) with blobs ``--blob-width`` times the channels' width, registered with
:func:`chic_register.pipeline.volume.register_volume` without slice indices (``chic-register solve VOLUME``). A pose
reported ok more than 0.5 mm (frame centre) or 0.5 deg off is a false lock; exit status 1 when there is one or a
crash. Complements ``hunt.py`` (single slices) and ``hunt_series.py`` (2-4 parallel slices).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PROTOCOL = {"neuro": ((0.5, 0.5, 2.0), (128, 128, 40)), "needle-guide": ((0.3, 0.3, 1.0), (128, 128, 40))}


def main(argv=None) -> int:
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec
    from chic_register.errors import NoLock
    from chic_register.imaging.simulate import simulate_volume
    from chic_register.model.pose import rigid, rot_y, rot_z
    from chic_register.pipeline.volume import register_volume
    from chic_register.studies.damage import FALSE_LOCK_DEG, FALSE_LOCK_MM, pose_error

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=40)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--blob-width", nargs=2, type=float, default=(1.5, 2.5), metavar=("LO", "HI"))
    args = ap.parse_args(argv)
    geoms = {name: geometry_of(load_spec(ROOT / "designs" / f"{name}.yaml")) for name in PROTOCOL}
    out, worst, cpu = Counter(), (0.0, 0.0), []
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(args.cases):
        rng = np.random.default_rng([args.seed, i])
        name = list(geoms)[i % len(geoms)]
        g = geoms[name]
        L = g.body.length
        tilt, az, tw = rng.uniform(0, 30), rng.uniform(0, 360), rng.uniform(-180, 180)
        width, snr = rng.uniform(*args.blob_width), rng.uniform(12, 30)
        shift = rng.uniform(-4, 4, 3)
        T_centre = rigid(rot_z(az) @ rot_y(tilt) @ rot_z(tw), shift)  # the body's centre placed at ``shift``
        T = T_centre @ rigid(np.eye(3), (0.0, 0.0, -L / 2))
        spacing, shape = PROTOCOL[name]
        sv = simulate_volume(g, T, shape, spacing, noise="rician", snr=snr, rng=rng, supersample=2,
                             thickness_samples=2, blob_width=width)
        c = time.process_time()
        try:
            reg = register_volume(sv.volume, g)
            tre, rot = pose_error(reg.T_scanner_from_fiducial, T, L)
            kind = "FALSE" if tre > FALSE_LOCK_MM or rot > FALSE_LOCK_DEG else "ok"
            if kind == "ok":
                worst = (max(worst[0], tre), max(worst[1], rot))
            note = f"tre {tre:.3f} mm rot {rot:.3f} deg, {len(reg.slices)} slices"
        except NoLock as exc:
            kind, note = "no_lock", exc.reason[:110]
        except Exception as exc:  # noqa: BLE001 (a crash is a finding)
            kind, note = "crash", f"{type(exc).__name__}: {exc}"[:110]
        cpu.append(time.process_time() - c)
        out[kind] += 1
        print(f"{i:4d} {name:12s} tilt {tilt:4.1f} width {width:.2f} snr {snr:4.1f} cpu {cpu[-1]:4.1f}s {kind:7s} {note}",
              flush=True)
    print(f"volumes {args.cases}: ok {out['ok']}, FALSE LOCKS {out['FALSE']}, no_lock {out['no_lock']}, crashes "
          f"{out['crash']}; largest error of a correct lock {worst[0]:.3f} mm, {worst[1]:.3f} deg; CPU per volume "
          f"median {np.median(cpu):.1f} s, max {max(cpu):.1f} s")
    print(f"wall {time.perf_counter() - t0:.0f} s, CPU {time.process_time() - c0:.0f} s; seed {args.seed}, blob width "
          f"{args.blob_width[0]:g}-{args.blob_width[1]:g}")
    return 1 if out["FALSE"] or out["crash"] else 0


if __name__ == "__main__":
    sys.exit(main())
