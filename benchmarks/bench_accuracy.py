"""Accuracy on the paper's simulation protocol (against the paper), and efficiency against the Cramér-Rao bound.

    .venv/bin/python benchmarks/bench_accuracy.py [--draws 20] [--levels 0.1 0.05 0.025 0.01] [--snr 20 50 | --snr]
        [--centroid-model on|off]
    .venv/bin/python benchmarks/bench_accuracy.py --crlb [--draws 100] [--snr 10 20 50] [--poses study grid]
        [--mode default|fast|centroid] [--draws-max M] [--json OUT.json]

Efficiency (``--crlb``): on the paper's study poses (its 18 cases, each
tilted case at a fixed azimuth) and on a grid of tilts 0-45 deg x depths
across the usable range (0.2-0.8 of the body), 2 mm slices with Rician
noise at each ``--snr``: the RMS error of the image normal, twist, depth and
TRE (at the body centre) over ``--draws`` noise draws, divided by the CRLB
(:mod:`chic_register.studies.efficiency`; of the sections of the tubes the slice plane
crosses, :func:`chic_register.precision.crlb.counted_tubes`: where the slab also grazes
a tube beyond its end, the ratios to the bound that counts that sliver too
follow on a second line), the noise-free error (bias), the solve
time (detect + pose wall, and CPU of the register() call) and the machine
load. The target: RMS / CRLB <= 1.15 for rotation and TRE at a median of
5 ms or less. Each ratio is printed with its 95 % bootstrap interval over the
draws ([lo-hi]); ``--draws-max M`` runs further batches of ``--draws`` at a
pose, up to M draws, while some interval there still contains 1.15 (every
draw run is kept). The summary counts, per metric, the poses whose interval
lies below 1.15 (met), above it (missed) or still contains it (undecided),
over the poses that locked in at least half their draws.

Paper study (default):

Runs :func:`chic_register.studies.evaluate.run_study` on designs/neuro.yaml (256 x 256,
0.5 mm pixels, thin sections) with the paper's uniform white noise at each
amplitude of ``--levels`` (fluid = 1, noise U(-a, a)) and with Rician noise at
``--snr``, and prints each group's max |error| and std beside the paper's
figures and the target (paper max / 3).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from chic_design.families import geometry_of
from chic_design.spec import load_spec
from chic_register.studies.efficiency import METRICS, pose_efficiency
from chic_register.studies.evaluate import PAPER, format_summary, paper_cases, run_study

ROOT = Path(__file__).resolve().parents[1]


MODES = {"default": {}, "fast": {"section_fit": False}, "centroid": {"centroid_model": True}}


def load_note() -> str:
    return f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores"


def efficiency_poses(geom, which) -> list[tuple[str, tuple]]:
    """``(label, (depth, tilt, azimuth, twist))`` of the study's cases and of the tilt x depth grid."""
    L = geom.body.length
    out = []
    if "study" in which:
        for i, c in enumerate(paper_cases(geom)):
            az = (30.0 + 47.0 * i) % 360.0 if c.random_azimuth else 0.0
            out.append((f"{c.group} {c.label}", (c.depth_mm, c.tilt_deg, az, c.twist_deg)))
    if "grid" in which:
        i = 0
        for tilt in (0.0, 15.0, 30.0, 45.0):
            for f in (0.2, 0.35, 0.5, 0.65, 0.8):
                out.append(("grid", (f * L, tilt, (37.0 * i) % 360.0, (23.0 * i) % 90.0 - 45.0)))
                i += 1
    return out


def run_efficiency(args, geom) -> None:
    """The ``--crlb`` benchmark (see the module docstring)."""
    opts = MODES[args.mode]
    snrs = args.snr if args.snr_given else [10.0, 20.0, 50.0]
    poses = efficiency_poses(geom, args.poses)
    record = {"command": " ".join(["benchmarks/bench_accuracy.py", "--crlb", "--draws", str(args.draws), "--snr",
                                   *[f"{v:g}" for v in snrs], "--poses", *args.poses, "--mode", args.mode,
                                   *(["--draws-max", str(args.draws_max)] if args.draws_max else [])]),
              "mode": args.mode, "load_before": os.getloadavg()[0], "runs": []}
    more = f" (up to {args.draws_max} where a 95 % interval contains 1.15)" if args.draws_max else ""
    print(f"{geom.name}: {len(poses)} poses x {args.draws} Rician draws{more} per SNR, 2 mm slices, 0.5 mm pixels, "
          f"mode {args.mode}; {load_note()}")
    for snr in snrs:
        t0, c0 = time.perf_counter(), time.process_time()
        print(f"\nRician SNR {snr:g}: RMS error / CRLB [95 % interval] (normal, twist, depth, TRE); draws; "
              f"noise-free error; solve ms (wall detect+pose | CPU call)")
        rows = []
        for k, (label, p) in enumerate(poses):
            r = pose_efficiency(geom, *p, snr=snr, draws=args.draws, seed=args.seed + k, register_options=opts,
                                draws_max=args.draws_max)
            rows.append((label, r))
            ratio = " ".join(f"{v:5.2f} [{lo:.2f}-{hi:.2f}]" for v, (lo, hi) in zip(r.ratio, r.ratio_ci))
            print(f"  {label:<10} depth {p[0]:5.1f} tilt {p[1]:4.0f} az {p[2]:5.1f} tw {p[3]:5.1f}: {ratio}  n {r.draws}  "
                  f"bias {r.bias[0]:.4f} deg {r.bias[2]:+.4f} mm  "
                  f"{np.median(r.ms) if r.ms.size else float('nan'):5.1f} | "
                  f"{np.median(r.cpu_ms) if r.cpu_ms.size else float('nan'):5.1f} ms"
                  f"{f'  ({r.no_lock} no-lock)' if r.no_lock else ''}", flush=True)
            if r.crlb_all is not None:
                print(f"{'':12}(the slab grazes a tube beyond its end: against the bound counting it too "
                      f"{' '.join(f'{v:5.2f}' for v in r.rms / r.crlb_all)})")
        ratios = np.array([r.ratio for _, r in rows])
        cis = np.array([r.ratio_ci for _, r in rows])  # (poses, 4, 2)
        ms = np.concatenate([r.ms for _, r in rows])
        cpu = np.concatenate([r.cpu_ms for _, r in rows])
        nolock = sum(r.no_lock for _, r in rows)
        locked = np.array([r.no_lock <= r.draws / 2 for _, r in rows])
        print(f"  summary over {len(rows)} poses ({nolock} no-locks of {sum(r.draws for _, r in rows)} draws; "
              f"{int(locked.sum())} poses locked in at least half their draws, the figures below over those):")
        for m, col, ci in zip(METRICS, ratios.T, cis.transpose(1, 0, 2)):
            u, ci = col[locked], ci[locked]
            met, missed = int(np.sum(ci[:, 1] < 1.15)), int(np.sum(ci[:, 0] > 1.15))
            print(f"    {m:>10}: median {np.nanmedian(u):.2f}, max {np.nanmax(u):.2f}, poses <= 1.15: "
                  f"{int(np.sum(u <= 1.15))}/{u.size}; 95 % interval below 1.15: {met}, above: {missed}, "
                  f"containing it: {u.size - met - missed}")
        print(f"    solve time: median {np.median(ms):.2f} ms wall (detect + pose), {np.median(cpu):.2f} ms CPU "
              f"(register call); {time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU for "
              f"this SNR; {load_note()}")
        record["runs"].append({"snr": snr, "poses": [{"label": lab, **r.to_dict()} for lab, r in rows],
                               "median_ms": float(np.median(ms)), "median_cpu_ms": float(np.median(cpu)),
                               "load_after": os.getloadavg()[0]})
    if args.json:
        from chic_register.util.atomic import write_json

        write_json(args.json, record)
        print(f"wrote {args.json}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--levels", type=float, nargs="+", default=[0.1, 0.05, 0.025, 0.01])
    ap.add_argument("--snr", type=float, nargs="*", default=None)
    ap.add_argument("--slice-thickness", type=float, default=0.0)
    ap.add_argument("--centroid-model", choices=("on", "off"), default="on",
                    help="solver's centroid model (default on, as the study)")
    ap.add_argument("--design", default=str(ROOT / "designs" / "neuro.yaml"))
    ap.add_argument("--crlb", action="store_true", help="efficiency against the Cramér-Rao bound instead")
    ap.add_argument("--poses", nargs="+", choices=("study", "grid"), default=["study", "grid"])
    ap.add_argument("--mode", choices=tuple(MODES), default="default", help="solver mode for --crlb")
    ap.add_argument("--draws-max", type=int, default=None,
                    help="--crlb: more batches of --draws, up to this many, where a ratio's 95 %% interval contains 1.15")
    ap.add_argument("--json", default=None, help="--crlb: also write every figure to this JSON file")
    args = ap.parse_args()
    args.snr_given = args.snr is not None
    if args.snr is None:
        args.snr = [20.0, 50.0]
    geom = geometry_of(load_spec(args.design))
    if args.crlb:
        run_efficiency(args, geom)
        return
    opts = {"centroid_model": args.centroid_model == "on"}
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
        print(f"detect + pose per slice: median {np.median(ms):.1f} ms ({time.perf_counter() - t0:.0f} s); "
              f"{load_note()}\n", flush=True)


if __name__ == "__main__":
    main()
