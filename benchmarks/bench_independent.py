"""Covariance calibration and CRLB efficiency on images the solver did not draw: the k-space model of the mesh.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_independent.py [--draws 30] [--snr 10 20 50] [--quick]
        [--filter none|hamming|tukey] [--mesh exports/neuro/body.stl --geometry exports/neuro/geometry.yaml]

The neuro design's body is built through the library (no files) and
tessellated as its ``body.stl`` is (or ``--mesh`` is read); each pose (the calibration study's four
and a tilt grid 0-45 deg) is rendered once, noise-free, by
:mod:`chic_register.studies.kspace` (256 x 256, 0.5 mm pixels, 2 mm sinc-pulse
slices), then registered with the default solver (verification on) on
``--draws`` Rician noise draws per SNR. Printed per SNR: locks; the mean
squared Mahalanobis length of the pose error under the reported covariance
(6 when calibrated); predicted over measured RMS TRE at the default target (1
when calibrated); RMS error over the CRLB (the bound of the solver's own image
model, :func:`chic_register.precision.crlb.pose_crlb`) for the image normal,
the twist and the TRE, pooled as RMS over the poses' ratios. Truth: the pose
rendered at; the noise-free slice's error (the bias of the solver's image
model on these images) is printed per pose first. Prints the CPU time and the load average.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from chic_design.cad.export import STL_ANGULAR_TOLERANCE_RAD, STL_TOLERANCE_MM  # noqa: E402
from chic_design.families import family_of  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402
from chic_register.errors import NoLock  # noqa: E402
from chic_register.model.geometry import load_geometry  # noqa: E402
from chic_register.pipeline.register import register  # noqa: E402
from chic_register.precision.crlb import Protocol, pose_crlb  # noqa: E402
from chic_register.precision.uncertainty import mahalanobis2, target_point  # noqa: E402
from chic_register.studies.calibration import pose_error  # noqa: E402
from chic_register.studies.efficiency import pose_errors  # noqa: E402
from chic_register.studies.kspace import kspace_image, read_body_mesh, slice_placement, with_noise  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The calibration study's poses (benchmarks/bench_uncertainty.py), then a tilt grid: (depth, tilt, azimuth, twist).
STUDY_POSES = [(35.0, 25.0, 300.0, 20.0), (22.0, 15.0, 30.0, 10.0), (30.0, 30.0, 100.0, 40.0), (15.0, 20.0, 200.0, 5.0)]
TILT_POSES = [(25.0, t, 60.0, 20.0) for t in (0.0, 15.0, 30.0, 45.0)]


def load_note() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} cores"


def neuro_mesh(spec_path: Path):
    """The neuro geometry and its body mesh (vertices (V, 3) mm, faces (F, 3)) in F, as ``body.stl`` holds it."""
    spec = load_spec(spec_path)
    family = family_of(spec)
    geom = family.geometry(spec, source={"spec": str(spec_path)})
    body = family.parts(spec, geom).body
    verts, faces = body.tessellate(STL_TOLERANCE_MM, STL_ANGULAR_TOLERANCE_RAD)
    return geom, np.array([[v.X, v.Y, v.Z] for v in verts]), np.asarray(faces, dtype=np.int64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=30, help="noise draws per pose and SNR (default 30)")
    ap.add_argument("--snr", type=float, nargs="+", default=[10.0, 20.0, 50.0])
    ap.add_argument("--filter", default="none", choices=("none", "hamming", "tukey"), help="k-space filter")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mesh", type=Path, help="a body.stl to render instead of the library's neuro body "
                    "(with --geometry: its geometry.yaml)")
    ap.add_argument("--geometry", type=Path, help="the geometry.yaml beside --mesh")
    ap.add_argument("--quick", action="store_true", help="two poses, 3 draws: a smoke run, not a measurement")
    args = ap.parse_args()
    c_start = time.process_time()
    print(f"before: {load_note()}")
    if args.mesh is not None:
        if args.geometry is None:
            ap.error("--mesh needs --geometry")
        geom, (V, F) = load_geometry(args.geometry), read_body_mesh(args.mesh)
    else:
        geom, V, F = neuro_mesh(ROOT / "designs" / "neuro.yaml")
    poses = STUDY_POSES + TILT_POSES
    draws = args.draws
    if args.quick:
        poses, draws = [STUDY_POSES[0], TILT_POSES[3]], 3
    target = target_point(geom)
    print(f"{geom.name}: body mesh {len(F)} triangles; {len(poses)} poses x {draws} draws per SNR, "
          f"256 x 256, 0.5 mm pixels, 2 mm slices, k-space filter {args.filter}; mesh + CAD {time.process_time() - c_start:.1f} s CPU")
    c0 = time.process_time()
    rendered = []
    for pose in poses:
        sl, T = slice_placement(*pose)
        rendered.append((pose, sl, T, kspace_image(V, F, geom.body, T, sl, kspace_filter=args.filter)))
    print(f"rendered {len(poses)} noise-free slices: {(time.process_time() - c0) / len(poses):.2f} s CPU each")
    for pose, sl, T, image in rendered:  # the noise-free error: the bias of the solver's model on these images
        try:
            e = pose_errors(register([with_noise(image, sl, None)], geom, target_F_mm=target).T_scanner_from_fiducial,
                            T, sl.T_scanner_from_image(), target)
            print(f"  noise-free {pose}: normal {e[0]:.4f} deg, twist {e[1]:+.4f} deg, depth {e[2]:+.4f} mm, "
                  f"TRE {e[3]:.4f} mm")
        except NoLock as exc:
            print(f"  noise-free {pose}: no lock ({exc})")
    rng = np.random.default_rng(args.seed)
    print(f"{'SNR':>4s} {'locks':>9s} {'Mahal^2':>8s} {'TREpred/meas':>12s} {'normal/CRLB':>11s} "
          f"{'twist/CRLB':>10s} {'TRE/CRLB':>9s} {'RMS TRE mm':>10s}")
    for snr in args.snr:
        protocol = Protocol(pixel_size_mm=0.5, slice_thickness_mm=2.0, snr=snr)
        m2, tre, pred, ratios, locks, tries, per_pose = [], [], [], [], 0, 0, []
        for pose, sl, T, image in rendered:
            bound = pose_crlb(geom, *pose, protocol, target)
            crlb = np.array([bound.sd_normal_deg, bound.sd_twist_deg, bound.tre_mm])
            errs = []
            for _ in range(draws):
                tries += 1
                noisy = with_noise(image, sl, snr, rng)
                try:
                    reg = register([noisy], geom, target_F_mm=target)
                except NoLock:
                    continue
                locks += 1
                T_est = reg.T_scanner_from_fiducial
                m2.append(mahalanobis2(pose_error(T, T_est), reg.uncertainty.covariance))
                e = pose_errors(T_est, T, noisy.T_scanner_from_image(), target)
                errs.append(e[[0, 1, 3]])
                tre.append(e[3])
                pred.append(reg.uncertainty.predicted_tre_mm)
            e = np.array(errs).reshape(-1, 3)
            r = np.sqrt(np.mean(e**2, axis=0)) / crlb if len(e) else np.full(3, np.nan)
            ratios.append(r)
            per_pose.append((pose, len(e), r))
        R = np.array(ratios)
        pooled = np.sqrt(np.nanmean(R**2, axis=0))
        tre, pred = np.array(tre), np.array(pred)
        ratio = float(np.sqrt(np.mean(pred**2) / np.mean(tre**2))) if tre.size else float("nan")
        print(f"{snr:4g} {locks:4d}/{tries:<4d} {np.mean(m2) if m2 else float('nan'):8.2f} {ratio:12.2f} "
              f"{pooled[0]:11.2f} {pooled[1]:10.2f} {pooled[2]:9.2f} "
              f"{np.sqrt(np.mean(tre**2)) if tre.size else float('nan'):10.3f}")
        for pose, n, r in per_pose:
            print(f"      pose {pose}: {n} locks, RMS/CRLB normal {r[0]:.2f}, twist {r[1]:.2f}, TRE {r[2]:.2f}")
    print(f"CPU time {time.process_time() - c_start:.1f} s; after: {load_note()}")


if __name__ == "__main__":
    main()
