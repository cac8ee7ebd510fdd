"""The Leksell G localizer box (designs/leksell-g-ct.yaml, leksell-g-mr.yaml): simulated CT and MR slices and
volumes against their truth, and the real slices of tests/data/real/leksell.

    .venv/bin/python benchmarks/bench_nlocalizer.py [--seeds 4]

For each case: how many lock, the TRE at the frame centre (F (0, 0, 60), Leksell (100, 100, 100)) of those
that do (RMS and largest), and the pose's own predicted TRE (median) beside it. Single slices tilted about
F's x and y axes (the box's two plates face along x: an axial slice fixes the turn about x only to second
order and is refused), the same slices axial, four parallel axial slices registered together, and a
24-slice MR volume registered whole and as two halves (the halves must agree within their uncertainty).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chic_design.families import family_named  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402
from chic_register.errors import ImprecisePose, NoLock  # noqa: E402
from chic_register.imaging.ct import CTScene  # noqa: E402
from chic_register.imaging.simulate import add_rician_noise, simulate_ct_slice, simulate_slice, simulate_volume  # noqa: E402
from chic_register.io.volumes import read_volume  # noqa: E402
from chic_register.model.pose import invert, rigid, rot_y, rot_z, slice_frame  # noqa: E402
from chic_register.options import SolveOptions  # noqa: E402
from chic_register.pipeline.register import register  # noqa: E402
from chic_register.pipeline.volume import register_volume  # noqa: E402

CENTRE = np.array([0.0, 0.0, 60.0, 1.0])
PRIOR = SolveOptions(prior=np.eye(4))
REAL = ROOT / "tests" / "data" / "real" / "leksell"


def box(name: str):
    return family_named("nlocalizer").geometry(load_spec(ROOT / "designs" / f"{name}.yaml"))


def tre(T, T_true) -> float:
    return float(np.linalg.norm((np.asarray(T) @ CENTRE - np.asarray(T_true) @ CENTRE)[:3]))


def outcome(slices, T_true, geom):
    """(locked, TRE mm, predicted TRE mm, reason)"""
    try:
        reg = register(slices, geom, options=PRIOR)
    except NoLock as exc:
        if isinstance(exc, ImprecisePose):
            axis = re.search(r"about (F's \w+ axis)", exc.reason)
            return False, math.nan, math.nan, "imprecise" + (f" (about {axis.group(1)})" if axis else "")
        return False, math.nan, math.nan, exc.reason.split("]: ")[-1][:60]
    return True, tre(reg.T_scanner_from_fiducial, T_true), reg.uncertainty.predicted_tre_mm, ""


def ct_slice(geom, depth, tilt, az, rng, skull):
    sim = simulate_ct_slice(geom, depth, tilt, az, rng.uniform(-5, 5), scene=CTScene(skull=skull), rng=rng)
    return [sim.slice], sim.truth.T_scanner_from_fiducial


def mr_slice(geom, depth, tilt, az, rng):
    sim = simulate_slice(geom, depth, tilt, az, rng.uniform(-5, 5), shape=(320, 320), pixel_spacing_mm=(0.8, 0.8),
                         slice_thickness_mm=2.0, rng=rng)
    sl = sim.slice
    sl = type(sl)(add_rician_noise(sl.pixels, 20.0, rng), sl.pixel_spacing_mm, sl.origin_mm, sl.col_dir, sl.row_dir,
                  sl.slice_thickness_mm, sl.source)
    return [sl], sim.truth.T_scanner_from_fiducial


def row(label: str, results) -> str:
    ok = [r for r in results if r[0]]
    errs = np.array([r[1] for r in ok])
    pred = np.array([r[2] for r in ok])
    reasons = sorted({r[3] for r in results if not r[0]})
    if ok:
        figures = (f"{np.sqrt(np.mean(errs ** 2)):.4f} | {errs.max():.4f} | {np.median(pred):.4f} | "
                   f"{np.sqrt(np.mean(errs ** 2)) / max(np.sqrt(np.mean(pred ** 2)), 1e-12):.2f}")
    else:
        figures = "- | - | - | -"
    return f"| {label} | {len(ok)}/{len(results)} | {figures} | {', '.join(reasons) or '-'} |"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4, help="poses per case (default 4)")
    args = ap.parse_args(argv)
    t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    ct, mr = box("leksell-g-ct"), box("leksell-g-mr")
    print("| case | locked | TRE RMS mm | TRE max mm | predicted TRE (median) mm | RMS / predicted | refusals |")
    print("|---|---|---|---|---|---|---|")
    for label, tilt, az in (("tilted 20 deg about x", 20, 90), ("tilted 15 deg about y", 15, 0),
                            ("tilted 25 deg about y", 25, 0), ("axial", 0, 0)):
        rng = np.random.default_rng(1)
        res = [outcome(*ct_slice(ct, 60 + rng.uniform(-15, 15), tilt, az, rng, s % 2 == 1), ct) for s in range(args.seeds)]
        print(row(f"CT slice, {label} (skull on every other)", res))
        rng = np.random.default_rng(2)
        res = [outcome(*mr_slice(mr, 60 + rng.uniform(-15, 15), tilt, az, rng), mr) for _ in range(args.seeds)]
        print(row(f"MR slice, {label} (SNR 20)", res))
    rng = np.random.default_rng(3)
    res = []
    for _ in range(args.seeds):
        # the box on a supine head, turned a little about each axis (well within --prior LPS's 60 deg), cut by
        # axial scanner slices
        T0 = rigid(rot_z(rng.uniform(-10, 10)) @ rot_y(rng.uniform(-3, 3)) @ rot_z(90) @ rot_y(rng.uniform(-3, 3)) @ rot_z(-90),
                   (rng.uniform(-5, 5), rng.uniform(-5, 5), -60.0))
        sims = [simulate_ct_slice(ct, d, 0.0, 0.0, T_scanner_from_fiducial=T0, rng=rng) for d in (30, 50, 70, 90)]
        res.append(outcome([s.slice for s in sims], T0, ct))
    print(row("CT, 4 parallel axial slices 20 mm apart, box turned up to 3 deg about x, y", res))
    halves = []
    for seed in range(args.seeds):
        T_true = invert(slice_frame(60.0, 3.0, (30.0, -30.0, 15.0, -15.0)[seed % 4], 2.0))  # turned 3 deg
        vol = simulate_volume(mr, T_true, (224, 224, 24), (1.0, 1.0, 2.0), blob_width=1.5, noise="rician", snr=20.0,
                              rng=seed).volume
        parts = []
        for ks in (None, list(range(12)), list(range(12, 24))):
            try:
                reg = register_volume(vol, mr, ks, options=PRIOR)
                parts.append((reg.T_scanner_from_fiducial, reg.uncertainty.predicted_tre_mm))
            except NoLock as exc:
                parts.append((None, type(exc).__name__))
        halves.append((T_true, parts))
    whole = [(p[0][0] is not None, tre(p[0][0], T) if p[0][0] is not None else math.nan,
              p[0][1] if p[0][0] is not None else math.nan, "" if p[0][0] is not None else p[0][1]) for T, p in halves]
    print(row("MR volume 224 x 224 x 24 (1 x 1 x 2 mm, blobs 1.5x, SNR 20), whole", whole))
    agree = []
    for T, p in halves:
        (Ta, ta), (Tb, tb) = p[1], p[2]
        if Ta is None or Tb is None:
            agree.append("refused")
            continue
        apart = tre(Ta, Tb)
        agree.append(f"{apart:.3f} mm apart, {apart / math.hypot(ta, tb):.1f} sigma")
    print()
    print("MR volume halves (slices 0-11 and 12-23), each seed: " + "; ".join(agree))
    print()
    print("Real slices (tests/data/real/leksell), `solve --prior LPS`:")
    for f in sorted(REAL.glob("*.nii.gz")):
        geom = ct if "_ct_" in f.name else mr
        sl = read_volume(f).native_slice(0)
        try:
            reg = register([sl], geom, options=PRIOR)
            print(f"- {f.name}: ok, residual RMS {reg.slices[0].residual_rms_mm:.3f} mm")
        except NoLock as exc:
            print(f"- {f.name}: refused: {exc.reason[:160]}")
    c1 = resource.getrusage(resource.RUSAGE_SELF)
    print(f"\nwall {time.perf_counter() - t0:.0f} s, CPU {c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime:.0f} s; "
          f"load average {os.getloadavg()[0]:.2f} at end; seeds {args.seeds}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
