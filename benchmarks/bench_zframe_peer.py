"""The project's Z-frame volume registration against its peer, 3D Slicer's ZFrameRegistration, on the same volumes.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_zframe_peer.py [--cases 40] [--seed 0] [--rod-error-mm 0.1 0.3]
        [--scale-factor 1] [--verbose]

The peer is ``benchmarks/peers/zframe_susil.py`` (Susil et al. 1999 as ZFrameRegistration applies it to the z001
frame). Each case is a simulated volume of ``designs/zframe.yaml`` drawn as real scans look: axial slices of
0.6-0.8 mm pixels, 2-3 mm thick, over 40-80 mm around the frame's middle (cutting its ends off or reaching past
them); the frame within 5 mm of the volume's centre, tilted 0-5 deg (a mounted template), any twist; Rician SNR
10-30; blobs 1.5-2.5x the rods; each rod's ends 0.1-0.3 mm off the design (the simulated frame's, not the one
registered with); and the scanner's scale, about the volume's centre: 0.2-1 % per in-plane axis and 1-3 % through
the slices (either sign; the volume declares the spacing the scanner would). The truth is the frame as the image
shows it: its centre (0, 0, 30) mm where the scale puts it, its rotation the frame's own (the rotation of the
apparent pose with the scale along the image's axes taken out; a rigid fit to the rods as shown turns 0.04 deg from
it, 0.12 at most). The project registers with
:func:`chic_register.pipeline.volume.register_volume` (``prior``: the truth's rotation, as the mount tells it), the
peer every slice (skipping those it cannot use). CPU per volume is each method's alone (``time.process_time``, the
same process, after a warm-up). Then both on the two real Z-frame scans in tests/data/real, and their difference.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent / "peers"))
from zframe_susil import register_zframe_volume  # noqa: E402

from chic_register.errors import NoLock  # noqa: E402
from chic_register.imaging.simulate import simulate_volume  # noqa: E402
from chic_register.io.volumes import read_volume  # noqa: E402
from chic_register.model.pose import rigid, rot_y, rot_z  # noqa: E402
from chic_register.pipeline.volume import register_volume  # noqa: E402

CENTRE_F = np.array([0.0, 0.0, 30.0, 1.0])
MATRIX = 256  # a real scan's in-plane matrix (0.6-0.8 mm pixels: a 154-205 mm field of view)
REAL = ROOT / "tests" / "data" / "real"
METHODS = ("project", "peer")
#: ZFrameRegistration's own pose of zframe-masked-b.nrrd on slices 6-11 (tests/data/real/README.md).
MASKED_B_REFERENCE = np.array([[-0.999919, 0.012362, 0.003162, 11.135927],
                               [-0.012422, -0.999728, -0.019757, -14.787442],
                               [0.002917, -0.019795, 0.999800, -136.789753],
                               [0.0, 0.0, 0.0, 1.0]])


def zframe_geometry():
    """The geometry file of ``designs/zframe.yaml``, written and read back as a user's would be."""
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec
    from chic_register.model.geometry import load_geometry, write_geometry

    with tempfile.TemporaryDirectory(prefix="zframe-peer-") as tmp:
        path = write_geometry(geometry_of(load_spec(ROOT / "designs" / "zframe.yaml"),
                                          source={"spec": "designs/zframe.yaml"}), Path(tmp) / "geometry.yaml")
        return load_geometry(path)


def moved_rods(geom, rng, lo_mm: float = 0.1, hi_mm: float = 0.3):
    """``geom`` with each rod's ends moved ``lo_mm``-``hi_mm`` across the rod, each its own way (a print's error)."""
    tubes = []
    for t in geom.tubes:
        ends = []
        for p in (t.p0, t.p1):
            v = rng.normal(size=3)
            v -= (v @ t.direction) * t.direction
            ends.append(tuple(np.asarray(p) + rng.uniform(lo_mm, hi_mm) * v / np.linalg.norm(v)))
        tubes.append(dataclasses.replace(t, p0=ends[0], p1=ends[1]))
    return dataclasses.replace(geom, tubes=tuple(tubes))


def draw_case(rng) -> dict:
    """One case's settings."""
    return {
        "pixel_mm": rng.uniform(0.6, 0.8), "slice_mm": rng.uniform(2.0, 3.0), "cover_mm": rng.uniform(40.0, 80.0),
        "offset_mm": rng.uniform(-5.0, 5.0, 3), "tilt_deg": rng.uniform(0.0, 5.0), "azimuth_deg": rng.uniform(0, 360),
        "twist_deg": rng.uniform(0, 360), "snr": rng.uniform(10.0, 30.0), "blob_width": rng.uniform(1.5, 2.5),
        "scale": np.r_[rng.uniform(0.002, 0.01, 2), rng.uniform(0.01, 0.03)] * rng.choice([-1.0, 1.0], 3),
    }


def build_case(geom, case: dict, rng, rod_error_mm=(0.1, 0.3)):
    """``(declared volume, T_true: the frame's rotation and its centre where the image shows it)``."""
    T = rigid(rot_z(case["azimuth_deg"]) @ rot_y(case["tilt_deg"]) @ rot_z(case["twist_deg"]), case["offset_mm"])
    T = T @ rigid(np.eye(3), -CENTRE_F[:3])  # the frame's centre at ``offset_mm`` from the volume's centre
    shape = (MATRIX, MATRIX, int(round(case["cover_mm"] / case["slice_mm"])))
    spacing = (case["pixel_mm"], case["pixel_mm"], case["slice_mm"])
    vol = simulate_volume(moved_rods(geom, rng, *rod_error_mm), T, shape, spacing, noise="rician", snr=case["snr"],
                          rng=rng, supersample=3, thickness_samples=6, blob_width=case["blob_width"]).volume
    M = np.diag(1.0 + case["scale"])  # the scanner's scale about its isocentre, the volume's centre (LPS origin)
    declared = dataclasses.replace(vol, spacing_mm=tuple(M.diagonal() * spacing), origin_mm=M @ vol.origin_mm)
    T_true = T.copy()
    T_true[:3, 3] = M @ (T @ CENTRE_F)[:3] - T[:3, :3] @ CENTRE_F[:3]
    return declared, T_true


def errors(T_est, T_true) -> tuple[float, float]:
    """(error at the frame centre in mm, rotation error in deg; from the sine and cosine, exact for small angles)."""
    D = T_est[:3, :3].T @ T_true[:3, :3]
    sin = 0.5 * np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]])
    rot = math.degrees(math.atan2(sin, 0.5 * (np.trace(D) - 1.0)))
    return float(np.linalg.norm((T_est @ CENTRE_F - T_true @ CENTRE_F)[:3])), rot


def run_project(volume, geom, prior_R):
    """``(T or None, slices used, note)``."""
    try:
        reg = register_volume(volume, geom, prior=rigid(prior_R, (0.0, 0.0, 0.0)))
    except NoLock as exc:
        return None, 0, exc.reason[:150]
    return reg.T_scanner_from_fiducial, len(reg.slices), ""


def run_peer(volume):
    """``(T or None, slices used, note)``."""
    T, info = register_zframe_volume(volume)
    used = sum(r.T_scanner_from_fiducial is not None for r in info)
    return T, used, "" if T is not None else "no slice passed"


def timed(fn, *args):
    """``fn(*args)`` with its CPU seconds appended."""
    c = time.process_time()
    out = fn(*args)
    return (*out, time.process_time() - c)


def summary(rows: list[dict], n_cases: int) -> list[str]:
    """Per method: registered cases, the errors' median and 90th percentile, CPU per volume."""
    lines = [f"{'method':8s} {'registered':>10s} {'rot deg p50':>11s} {'p90':>7s} {'centre mm p50':>13s} {'p90':>7s} "
             f"{'> 0.5 mm or deg':>15s} {'CPU s/vol p50':>13s} {'p90':>6s}"]
    for m in METHODS:
        ok = [r for r in rows if r[m]["T"] is not None]
        rot = np.array([r[m]["rot"] for r in ok]) if ok else np.array([math.nan])
        tre = np.array([r[m]["tre"] for r in ok]) if ok else np.array([math.nan])
        cpu = np.array([r[m]["cpu"] for r in rows])
        far = int(np.sum((rot > 0.5) | (tre > 0.5))) if ok else 0
        lines.append(f"{m:8s} {len(ok):>4d} of {n_cases:<3d} {np.median(rot):11.3f} {np.percentile(rot, 90):7.3f} "
                     f"{np.median(tre):13.3f} {np.percentile(tre, 90):7.3f} {far:15d} {np.median(cpu):13.3f} "
                     f"{np.percentile(cpu, 90):6.3f}")
    return lines


SPLITS = (
    ("tilt < 2.5 deg", lambda c: c["tilt_deg"] < 2.5), ("tilt >= 2.5 deg", lambda c: c["tilt_deg"] >= 2.5),
    ("SNR < 20", lambda c: c["snr"] < 20), ("SNR >= 20", lambda c: c["snr"] >= 20),
    ("blobs < 2x", lambda c: c["blob_width"] < 2), ("blobs >= 2x", lambda c: c["blob_width"] >= 2),
    ("|z scale| < 2 %", lambda c: abs(c["scale"][2]) < 0.02),
    ("|z scale| >= 2 %", lambda c: abs(c["scale"][2]) >= 0.02),
    ("slices < 2.5 mm", lambda c: c["slice_mm"] < 2.5), ("slices >= 2.5 mm", lambda c: c["slice_mm"] >= 2.5),
    ("cover < 60 mm", lambda c: c["cover_mm"] < 60), ("cover >= 60 mm", lambda c: c["cover_mm"] >= 60),
)


def paired(rows: list[dict]) -> list[str]:
    """Cases both registered, by kind: each method's median errors and how often the project is the closer."""
    both = [r for r in rows if all(r[m]["T"] is not None for m in METHODS)]
    lines = [f"{'cases both registered':22s} {'n':>3s} | {'rot deg: project':>16s} {'peer':>6s} "
             f"{'project closer':>14s} | {'centre mm: project':>18s} {'peer':>6s} {'project closer':>14s}"]
    for name, keep in (("all", lambda c: True), *SPLITS):
        rs = [r for r in both if keep(r["case"])]
        if not rs:
            continue
        cells = []
        for key in ("rot", "tre"):
            a, b = (np.array([r[m][key] for r in rs]) for m in METHODS)
            cells.append(f"{np.median(a):{16 if key == 'rot' else 18}.3f} {np.median(b):6.3f} "
                         f"{int(np.sum(a < b)):>7d} of {len(rs):<3d}")
        lines.append(f"{name:22s} {len(rs):3d} | {cells[0]} | {cells[1]}")
    return lines


def real_scans(geom) -> list[str]:
    """Both methods on the real scans (prior: the frame's x, y, z along the scanner's R, A, S), their difference, and
    each against ZFrameRegistration's own pose of the masked scan (tests/data/real/README.md, slices 6-11)."""
    from chic_register.cli.inputs import load_prior

    prior_R = load_prior("RAS")[:3, :3]
    lines = []
    for name in ("zframe-masked-b.nrrd", "zframe-clinical-3t.nrrd"):
        vol = read_volume(REAL / name)
        Tp, n_p, note_p, cpu_p = timed(run_project, vol, geom, prior_R)
        c = time.process_time()
        T, info = register_zframe_volume(vol)
        cpu_q = time.process_time() - c
        used = [r.k for r in info if r.T_scanner_from_fiducial is not None]
        lines.append(f"{name}: project {'%d slices' % n_p if Tp is not None else 'no pose: ' + note_p}, "
                     f"CPU {cpu_p:.2f} s; peer slices {ranges(used) or 'none'}, CPU {cpu_q:.3f} s")
        if T is not None and Tp is not None:
            tre, rot = errors(T, Tp)
            lines.append(f"  peer - project: {tre:.3f} mm at the frame centre, {rot:.3f} deg; centre moved "
                         f"{np.array2string((T @ CENTRE_F - Tp @ CENTRE_F)[:3], precision=3)} mm (LPS)")
        if name == "zframe-masked-b.nrrd":
            T_611, _ = register_zframe_volume(vol, range(6, 12))
            for label, X in (("project", Tp), (f"peer, slices {ranges(used)}", T), ("peer, slices 6-11", T_611)):
                if X is not None:
                    tre, rot = errors(X, MASKED_B_REFERENCE)
                    lines.append(f"  {label} - ZFrameRegistration's pose (slices 6-11): {tre:.4f} mm, {rot:.4f} deg")
        if T is None:
            lines.extend("  " + line for line in peer_failures(vol, info, Tp, geom))
    return lines


def peer_failures(vol, info, T_project, geom) -> list[str]:
    """Why the peer found nothing: its reasons, and how many of its seven peaks lie on a rod the project's pose puts
    in the slice (within 3 mm)."""
    from collections import Counter

    reasons = Counter(r.reason for r in info)
    out = ["peer skipped every slice: " + "; ".join(f"{n} x {why}" for why, n in reasons.most_common())]
    if T_project is None:
        return out
    on_rods = []
    for r in info:
        sl = vol.native_slice(r.k)
        if r.points_mm is None or not len(r.points_mm):
            continue
        S = sl.T_scanner_from_image()
        pts = r.points_mm @ S[:3, :2].T + S[:3, 3]
        T_F_from_S = np.linalg.inv(T_project) @ S
        rods = [p for p in geom.intersect_plane(T_F_from_S[:3, 3], T_F_from_S[:3, 2]).values() if len(p)]
        if not rods:
            continue
        rods_S = np.array([(T_project @ np.append(p[0], 1.0))[:3] for p in rods])
        d = np.linalg.norm(pts[:, None, :] - rods_S[None, :, :], axis=2).min(axis=1)
        on_rods.append(int(np.sum(d < 3.0)))
    if on_rods:
        out.append(f"its peaks within 3 mm of a rod of the project's pose, per slice: {' '.join(map(str, on_rods))} "
                   "(of 7)")
    return out


def ranges(ks: list[int]) -> str:
    """``[5, 6, 7, 9]`` as ``5-7, 9``."""
    out, start = [], None
    for i, k in enumerate(ks):
        start = k if start is None else start
        if i + 1 == len(ks) or ks[i + 1] != k + 1:
            out.append(f"{start}-{k}" if k != start else f"{k}")
            start = None
    return ", ".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rod-error-mm", nargs=2, type=float, default=(0.1, 0.3), metavar=("LO", "HI"),
                    help="how far each rod end is moved across the rod (0 0: the frame as designed)")
    ap.add_argument("--scale-factor", type=float, default=1.0, help="times the drawn scanner scale (0: none)")
    ap.add_argument("--verbose", action="store_true", help="a line per case")
    args = ap.parse_args(argv)
    geom = zframe_geometry()
    c0 = time.process_time()
    warm, _ = build_case(geom, draw_case(np.random.default_rng([args.seed, 1 << 20])),
                         np.random.default_rng([args.seed, 1 << 20, 1]))
    run_project(warm, geom, np.eye(3))
    run_peer(warm)
    rows = []
    for i in range(args.cases):
        rng = np.random.default_rng([args.seed, i])
        case = draw_case(rng)
        case["scale"] = args.scale_factor * case["scale"]
        vol, T_true = build_case(geom, case, rng, args.rod_error_mm)
        row = {"case": case}
        for m, fn, fargs in (("project", run_project, (vol, geom, T_true[:3, :3])), ("peer", run_peer, (vol,))):
            T, used, note, cpu = timed(fn, *fargs)
            tre, rot = errors(T, T_true) if T is not None else (math.nan, math.nan)
            row[m] = {"T": T, "used": used, "note": note, "cpu": cpu, "tre": tre, "rot": rot}
        rows.append(row)
        if args.verbose:
            print(f"{i:3d} px {case['pixel_mm']:.2f} sl {case['slice_mm']:.2f} cover {case['cover_mm']:4.1f} "
                  f"tilt {case['tilt_deg']:3.1f} snr {case['snr']:4.1f} w {case['blob_width']:.2f} scale "
                  f"{' '.join(f'{100 * s:+.1f}' for s in case['scale'])} % | "
                  + " | ".join(f"{m} {row[m]['used']:2d} sl {row[m]['tre']:.3f} mm {row[m]['rot']:.3f} deg "
                               f"{row[m]['cpu']:.2f} s {row[m]['note']}" for m in METHODS), flush=True)
    print(f"{args.cases} simulated z001 volumes (seed {args.seed}, rod ends {args.rod_error_mm[0]:g}-"
          f"{args.rod_error_mm[1]:g} mm off, scanner scale x {args.scale_factor:g}); errors against the frame as the "
          "image shows it, over the cases each method registered")
    print("\n".join(summary(rows, args.cases)))
    for i, r in enumerate(rows):
        for m in METHODS:
            if r[m]["T"] is None:
                print(f"  {m} registered no pose in case {i}: {r[m]['note']}")
    print()
    print("\n".join(paired(rows)))
    print()
    print("real scans (tests/data/real), prior RAS:")
    print("\n".join(real_scans(geom)))
    print(f"CPU {time.process_time() - c0:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
