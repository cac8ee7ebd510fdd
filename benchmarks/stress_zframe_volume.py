"""Stress the Z-frame solver with volumes that look like real scans, through the CLI, against the truth.

    PYTHONPATH=. .venv/bin/python benchmarks/stress_zframe_volume.py [--cases 60] [--seed 0]
        [--geometry exports/zframe/geometry.yaml] [--case INDEX] [--keep DIR]

Every case is a volume of the z001 Z-frame (``designs/zframe.yaml``) drawn with
what real scanner volumes do, each stress on or off at random (``STRESSES``):

- always: blobs 1.5-2.5x the rod diameter, Rician SNR 8-30, slices 1-3 mm, the
  frame tilted 0-28 deg from the slice normal (its computed limit is 30.7 deg at
  mid-depth) with any twist;
- ``unequal``: each rod's fluid signal x U(0.6, 1.4);
- ``bubble``: one or two rods dark over 2-6 mm (an air bubble);
- ``bias``: a linear bias field and a surface-coil fall-off (signal x 0.25-1 across the frame);
- ``gaps``: slices spaced 1.2-1.8x their thickness;
- ``past``: 10-40 mm of empty slices beyond each end of the frame;
- ``cutoff``: the volume covers only 25-45 mm of the frame's height;
- ``tissue``: a bright tissue ellipsoid beside the frame, near two rods;
- ``plate``: a grid-template plate (a bright slab with a grid of holes) beside the frame;
- ``phantom``: a bright 50-70 mm cylinder phantom beside the frame;
- ``aniso``: in-plane voxels of different row and column size (0.5-1.2 mm);
- ``oblique``: a volume stored with a random rotation as direction cosines
  (NRRD ``space directions``, DICOM oblique ImageOrientationPatient), right- or
  left-handed, or coronal / sagittal (left-handed) axes;
- ``int16``: voxels stored as int16 with a large offset and scale (a DICOM
  series always stores int16 with rescale).

The volume is written as NRRD, NIfTI or a DICOM series with the project's
writer, then solved with ``chic_register.cli.main.main(["solve", ..., "--json"])``
twice: with ``--prior`` (a JSON pose turned up to 30 deg and shifted up to 10 mm
from the truth) and without. Outcomes: ``ok`` (target error at the frame centre
<= 0.5 mm and rotation error <= 0.5 deg), ``false`` (an ``ok`` beyond that),
``refused`` (no_lock, exit 3), ``error`` (exit 2), ``crash`` (a traceback).
Without a prior the symmetric z001 frame must be refused (or locked right).
Cases are seeded one by one (``default_rng([seed, index])``). Prints a table by
stress; exit 1 on a false lock or a crash.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STRESSES = ("unequal", "bubble", "bias", "gaps", "past", "cutoff", "tissue", "plate", "phantom", "aniso",
            "oblique", "int16")
FALSE_LOCK_MM = 0.5
FALSE_LOCK_DEG = 0.5
CENTRE_F = np.array([0.0, 0.0, 30.0])


def _rotation(axis, angle_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    a = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(a / np.linalg.norm(a) * math.radians(angle_deg)).as_matrix()


def _random_rotation(rng) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=int(rng.integers(1 << 31))).as_matrix()


def draw_case(rng, p_stress: float = 0.35) -> dict:
    """Settings of one case (plain numbers and lists: JSON-ready)."""
    on = {s: bool(rng.random() < p_stress) for s in STRESSES}
    if on["past"] and on["cutoff"]:
        on[("past", "cutoff")[int(rng.integers(2))]] = False
    thick = float(rng.uniform(1.0, 3.0))
    gap = float(rng.uniform(0.2, 0.8)) * thick if on["gaps"] else 0.0
    pix = float(rng.uniform(0.5, 1.1))
    pix_ij = [pix, pix] if not on["aniso"] else [float(rng.uniform(0.5, 1.2)), float(rng.uniform(0.5, 1.2))]
    case = {
        "stresses": [s for s in STRESSES if on[s]],
        "blob_width": float(rng.uniform(1.5, 2.5)),
        "snr": float(rng.uniform(8.0, 30.0)),
        "thickness_mm": thick,
        "spacing_k_mm": thick + gap,
        "pixel_ij_mm": pix_ij,
        "tilt_deg": float(rng.uniform(0.0, 28.0)),
        "tilt_axis_deg": float(rng.uniform(0, 360)),
        "twist_deg": float(rng.uniform(0, 360)),
        "offset_mm": rng.uniform(-10, 10, 2).tolist(),
        "signal": float(rng.uniform(200, 3000)),
        "format": ["nrrd", "nii.gz", "dicom"][int(rng.integers(3))],
        "rod_gain": (rng.uniform(0.6, 1.4, 7) if on["unequal"] else np.ones(7)).tolist(),
        "bubbles": [[int(rng.integers(7)), float(rng.uniform(8, 52)), float(rng.uniform(2, 6))]
                    for _ in range(int(rng.integers(1, 3)))] if on["bubble"] else [],
        "bias": {"gradient": rng.normal(0, 1, 3).tolist(), "gain_min": float(rng.uniform(0.25, 0.6)),
                 "coil_mm": float(rng.uniform(40, 90)), "coil_dir": rng.normal(0, 1, 3).tolist()} if on["bias"] else None,
        "past_mm": float(rng.uniform(10, 40)) if on["past"] else float(rng.uniform(-2, 4)),
        "cover_mm": float(rng.uniform(25, 45)) if on["cutoff"] else None,
        "cover_start_mm": float(rng.uniform(0, 20)),
        "tissue": {"signal": float(rng.uniform(0.3, 0.9)), "side": int(rng.integers(4)),
                   "gap_mm": float(rng.uniform(2, 12))} if on["tissue"] else None,
        "plate": {"signal": float(rng.uniform(0.4, 1.0)), "side": int(rng.integers(4)),
                  "gap_mm": float(rng.uniform(3, 15))} if on["plate"] else None,
        "phantom": {"signal": float(rng.uniform(0.4, 1.0)), "side": int(rng.integers(4)),
                    "diameter_mm": float(rng.uniform(50, 70)), "gap_mm": float(rng.uniform(3, 20))}
        if on["phantom"] else None,
        "direction": None,
        "int16": on["int16"],
        "prior_turn_deg": float(rng.uniform(0, 30)),
        "prior_axis": rng.normal(0, 1, 3).tolist(),
        "prior_shift_mm": rng.uniform(-10, 10, 3).tolist(),
    }
    if on["oblique"]:
        kind = int(rng.integers(3))
        if kind == 0:  # any rotation, stored right- or left-handed (k reversed)
            case["direction"] = (_random_rotation(rng) @ np.diag([1.0, 1.0, rng.choice([-1.0, 1.0])])).tolist()
        elif kind == 1:  # coronal: i = L, j = -S (rows go down to the feet), k = P
            case["direction"] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
        else:  # sagittal: i = P, j = -S, k = L
            case["direction"] = [[0, 0, 1], [1, 0, 0], [0, -1, 0]]
    return case


def _side_vec(side: int) -> np.ndarray:
    return [np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([-1.0, 0, 0]), np.array([0, -1.0, 0])][side]


def _extras_F(points_F: np.ndarray, case: dict) -> np.ndarray:
    """Signal (fraction of fluid) of the bright structures beside the frame at points of F, shape (N,)."""
    out = np.zeros(len(points_F))
    x, y, z = points_F.T
    if case["tissue"]:
        t = case["tissue"]
        n = _side_vec(t["side"])
        c = n * (30 + t["gap_mm"] + 25) + np.array([0, 0, 30.0])
        d = points_F - c
        along = d @ n
        perp = d - along[:, None] * n
        r2 = (along / 25.0) ** 2 + (np.hypot(perp[:, 0], perp[:, 1]) / 45.0) ** 2 + (perp[:, 2] / 60.0) ** 2
        out = np.maximum(out, t["signal"] * (r2 <= 1.0) * (1.0 + 0.2 * np.sin(0.3 * x) * np.cos(0.25 * y)))
    if case["plate"]:
        p = case["plate"]
        n = _side_vec(p["side"])
        along = points_F @ n - (30 + p["gap_mm"])
        lateral = points_F @ np.array([-n[1], n[0], 0.0])
        slab = (along >= 0) & (along <= 8) & (np.abs(lateral) <= 45) & (z >= -5) & (z <= 65)
        hole = (np.hypot((lateral + 45) % 5 - 2.5, (z + 5) % 5 - 2.5) < 1.0)
        out = np.maximum(out, p["signal"] * (slab & ~hole))
    if case["phantom"]:
        ph = case["phantom"]
        n = _side_vec(ph["side"])
        r = ph["diameter_mm"] / 2
        c = n * (30 + ph["gap_mm"] + r)
        d = points_F[:, :2] - c[:2]
        out = np.maximum(out, ph["signal"] * (np.hypot(d[:, 0], d[:, 1]) <= r) * (z >= -20) * (z <= 80))
    return out


def build_volume(geom, case: dict):
    """(Volume, T_scanner_from_fiducial) of one case."""
    from scipy.ndimage import gaussian_filter

    from chic_register.imaging.blob_width import render_tubes_widened
    from chic_register.imaging.simulate import add_rician_noise
    from chic_register.io.volumes import Volume, plane_frame

    rng = np.random.default_rng(case["rng_seed"])
    D = np.eye(3) if case["direction"] is None else np.asarray(case["direction"], dtype=float)
    tilt_axis = _rotation([0, 0, 1], case["tilt_axis_deg"]) @ np.array([1.0, 0, 0])
    R_vol_from_F = _rotation(tilt_axis, case["tilt_deg"]) @ _rotation([0, 0, 1], case["twist_deg"])
    # the frame's pose is a rotation whatever the volume's handedness (a left-handed storage, det D = -1, is common)
    R_sf = D @ np.diag([1.0, 1.0, np.sign(np.linalg.det(D))]) @ R_vol_from_F
    si, sj = case["pixel_ij_mm"]
    sk, thick = case["spacing_k_mm"], case["thickness_mm"]
    # extent: the frame's corners along the volume axes
    corners = np.array([[x, y, z] for x in (-36, 36) for y in (-36, 36) for z in (0, 60)], dtype=float)
    cv = (corners - CENTRE_F) @ R_vol_from_F.T  # in volume axes, centre of frame at 0
    half_ij = np.abs(cv[:, :2]).max(axis=0) + 25.0
    if case["phantom"] or case["plate"] or case["tissue"]:
        half_ij = half_ij + 25.0
    k_lo, k_hi = cv[:, 2].min(), cv[:, 2].max()
    axis_k = R_vol_from_F[2, 2]  # the frame's z along k
    if case["cover_mm"] is not None:  # cover part of the frame's height
        a = case["cover_start_mm"] - 30.0
        k_lo, k_hi = sorted((a * axis_k, (a + case["cover_mm"]) * axis_k))
    else:
        k_lo, k_hi = k_lo - case["past_mm"], k_hi + case["past_mm"]
    ni, nj = (int(math.ceil(2 * half_ij[0] / si)) + 1, int(math.ceil(2 * half_ij[1] / sj)) + 1)
    nk = max(2, int(math.ceil((k_hi - k_lo) / sk)) + 1)
    off = np.array([*case["offset_mm"], 0.0])
    origin_vol = np.array([-(ni - 1) * si / 2, -(nj - 1) * sj / 2, k_lo]) + off  # voxel 0 in volume axes
    origin = D @ origin_vol
    T_sf = np.eye(4)
    T_sf[:3, :3] = R_sf
    T_sf[:3, 3] = -R_sf @ CENTRE_F  # frame centre at the scanner origin
    T_fs = np.linalg.inv(T_sf)

    tubes = [[t] for t in geom.tubes]
    for rod, z_mm, length in case["bubbles"]:  # a dark stretch: the rod in two pieces (its z runs 0..60 mm)
        t = geom.tubes[rod]
        p0, p1 = np.asarray(t.p0, float), np.asarray(t.p1, float)
        u0, u1 = (z_mm - length / 2) / 60.0, (z_mm + length / 2) / 60.0
        pieces = []
        for piece in tubes[rod]:
            a0, a1 = (np.asarray(piece.p0, float) - p0)[2] / 60.0, (np.asarray(piece.p1, float) - p0)[2] / 60.0
            if a0 < u0:
                pieces.append(replace(piece, p1=tuple(p0 + min(u0, a1) * (p1 - p0))))
            if a1 > u1:
                pieces.append(replace(piece, p0=tuple(p0 + max(u1, a0) * (p1 - p0))))
        tubes[rod] = pieces
    grid = Volume(np.zeros((1, 1, 1)), (si, sj, sk), origin, D)
    vox = np.zeros((nk, nj, ni))
    jj, ii = np.mgrid[0:nj, 0:ni]
    for k in range(nk):
        T_F_from_S = T_fs @ plane_frame(grid, k)
        layer = np.zeros((nj, ni))
        for g, t in zip(case["rod_gain"], tubes):
            if not t:
                continue
            img = render_tubes_widened(t, T_F_from_S, (nj, ni), (sj, si), thick, center_px=(0.0, 0.0),
                                       supersample=2, thickness_samples=3, blob_width=case["blob_width"])
            layer = np.maximum(layer, g * img)
        if case["tissue"] or case["plate"] or case["phantom"]:
            pts_S = np.stack([ii.ravel() * si, jj.ravel() * sj, np.zeros(ii.size)], axis=1)
            pts_F = pts_S @ T_F_from_S[:3, :3].T + T_F_from_S[:3, 3]
            ex = _extras_F(pts_F, case).reshape(nj, ni)
            ex = gaussian_filter(ex, (1.0 / sj, 1.0 / si))
            layer = np.maximum(layer, ex)
        if case["bias"]:
            b = case["bias"]
            ijk = np.stack([ii * si, jj * sj, np.full(ii.shape, k * sk)], axis=-1) + origin_vol
            p = ijk.reshape(-1, 3) @ D.T  # scanner mm
            grad = np.asarray(b["gradient"]) / (np.linalg.norm(b["gradient"]) + 1e-9)
            lin = 1.0 + (1.0 - b["gain_min"]) * 0.5 * np.clip(p @ grad / 40.0, -1, 1)
            cd = np.asarray(b["coil_dir"]) / (np.linalg.norm(b["coil_dir"]) + 1e-9)
            coil_pt = cd * 70.0
            dist = np.linalg.norm(p - coil_pt, axis=1)
            coil = 1.0 / (1.0 + (dist / b["coil_mm"]) ** 2)
            coil = coil / coil.max()
            field = np.clip(lin * (b["gain_min"] + (1 - b["gain_min"]) * coil), 0.1, 1.5)
            layer = layer * field.reshape(nj, ni)
        vox[k] = layer
    vox = case["signal"] * add_rician_noise(vox, case["snr"], rng)
    if case["int16"]:
        vox = np.clip(np.rint(vox * 3.7 + 1024), -32768, 32767).astype(np.int16)
    else:
        vox = vox.astype(np.float32)
    try:
        return Volume(vox, (si, sj, sk), origin, D, "<stress>", slice_thickness_mm=thick), T_sf
    except TypeError:  # a checkout from before volumes knew their slice thickness (the "before" figures)
        return Volume(vox, (si, sj, sk), origin, D, "<stress>"), T_sf


def usable_slices(geom, vol, T_sf, thickness_mm: float) -> int:
    """How many k-planes the design's plane checks pass (all rods visible and apart at nominal width)."""
    from chic_register.io.volumes import plane_frame
    from chic_register.model.envelope import plane_status
    from chic_register.model.pose import slice_angles

    T_fs = np.linalg.inv(T_sf)
    n = 0
    for k in range(vol.shape[0]):
        a = slice_angles(T_fs @ plane_frame(vol, k))
        n += bool(plane_status(geom, a.depth_mm, a.tilt_deg, a.azimuth_deg, max(vol.spacing_mm[:2]),
                               thickness_mm).ok)
    return n


def _pose_error(T_est, T_true) -> tuple[float, float]:
    c = np.append(CENTRE_F, 1.0)
    tre = float(np.linalg.norm((T_est @ c - T_true @ c)[:3]))
    R = T_est[:3, :3].T @ T_true[:3, :3]
    ang = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2))))
    return tre, ang


def solve_cli(path, geometry, prior=None) -> dict:
    """Run ``chic-register solve PATH --geometry G [--prior P] --json``: (exit code, JSON or None, stderr, cpu s)."""
    from chic_register.cli import main as cli

    argv = ["solve", str(path), "--geometry", str(geometry), "--json"]
    if prior is not None:
        argv += ["--prior", str(prior)]
    out, err = io.StringIO(), io.StringIO()
    t0 = time.process_time()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli.main(argv)
    except Exception:  # noqa: BLE001 (the point: a traceback is a finding)
        return {"code": None, "doc": None, "stderr": traceback.format_exc(), "cpu_s": time.process_time() - t0}
    try:
        doc = json.loads(out.getvalue()) if out.getvalue().strip() else None
    except json.JSONDecodeError:
        doc = None
    return {"code": code, "doc": doc, "stderr": err.getvalue(), "cpu_s": time.process_time() - t0}


def classify(res: dict, T_true) -> tuple[str, str]:
    """(outcome, detail)."""
    if res["code"] is None:
        return "crash", res["stderr"].strip().splitlines()[-1]
    doc = res["doc"] or {}
    if res["code"] == 0 and doc.get("status") == "ok":
        tre, ang = _pose_error(np.asarray(doc["T_scanner_from_fiducial"]), T_true)
        detail = f"tre {tre:.3f} mm, rot {ang:.3f} deg, used {doc.get('n_slices_used')}"
        return ("false" if tre > FALSE_LOCK_MM or ang > FALSE_LOCK_DEG else "ok"), detail
    if res["code"] == 3:
        return "refused", str(doc.get("reason", ""))[:300]
    if res["code"] == 2:
        return "error", res["stderr"].strip()[:300]
    return "crash", f"exit {res['code']}: {res['stderr'].strip()[:300]}"


def run_case(index: int, seed: int, geometry: Path, keep: Path | None = None) -> dict:
    from chic_register.io.volumes import write_volume
    from chic_register.model.geometry import load_geometry

    rng = np.random.default_rng([seed, index])
    case = draw_case(rng)
    case["rng_seed"] = [seed, index, 1]
    geom = load_geometry(geometry)
    t0 = time.process_time()
    vol, T_true = build_volume(geom, case)
    build_s = time.process_time() - t0
    usable = usable_slices(geom, vol, T_true, case["thickness_mm"])
    with tempfile.TemporaryDirectory(prefix="stress-") as tmp:
        folder = keep if keep is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / ("vol" if case["format"] == "dicom" else f"vol.{case['format']}")
        write_volume(vol, path)
        R = _rotation(case["prior_axis"], case["prior_turn_deg"]) @ T_true[:3, :3]
        T_prior = np.eye(4)
        T_prior[:3, :3], T_prior[:3, 3] = R, T_true[:3, 3] + np.asarray(case["prior_shift_mm"])
        prior = folder / "prior.json"
        prior.write_text(json.dumps({"T_scanner_from_fiducial": T_prior.tolist()}))
        (folder / "truth.json").write_text(json.dumps({"T_scanner_from_fiducial": T_true.tolist(), "case": case}))
        with_prior = solve_cli(path, geometry, prior)
        without = solve_cli(path, geometry, None)
    o1, d1 = classify(with_prior, T_true)
    o2, d2 = classify(without, T_true)
    return {"index": index, "stresses": case["stresses"], "format": case["format"], "tilt": case["tilt_deg"],
            "blob_width": case["blob_width"], "snr": case["snr"], "shape": list(vol.shape), "usable": usable,
            "prior": o1, "prior_detail": d1, "prior_cpu_s": with_prior["cpu_s"],
            "noprior": o2, "noprior_detail": d2, "noprior_cpu_s": without["cpu_s"], "build_cpu_s": build_s,
            "traceback": "\n".join(r["stderr"] for r in (with_prior, without) if r["code"] is None)}


OUTCOMES = ("ok", "refused", "false", "error", "crash")


def table(results: list[dict]) -> str:
    rows = [("all", results)] + [(s, [r for r in results if s in r["stresses"]]) for s in STRESSES]
    rows += [(f"tilt {a}-{b}", [r for r in results if a <= r["tilt"] < b]) for a, b in ((0, 10), (10, 20), (20, 30))]
    rows += [("usable >= 3", [r for r in results if r["usable"] >= 3]), ("usable < 3", [r for r in results if r["usable"] < 3])]
    rows += [(f"fmt {f}", [r for r in results if r["format"] == f]) for f in ("nrrd", "nii.gz", "dicom")]
    head = f"{'condition':<14}{'n':>4} | with prior: " + " ".join(f"{o:>7}" for o in OUTCOMES)
    head += " | no prior: " + " ".join(f"{o:>7}" for o in OUTCOMES)
    lines = [head]
    for name, rs in rows:
        if not rs:
            continue
        a = " ".join(f"{sum(r['prior'] == o for r in rs):>7}" for o in OUTCOMES)
        b = " ".join(f"{sum(r['noprior'] == o for r in rs):>7}" for o in OUTCOMES)
        lines.append(f"{name:<14}{len(rs):>4} | {'':12}{a} | {'':10}{b}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--geometry", type=Path, default=ROOT / "exports" / "zframe" / "geometry.yaml")
    ap.add_argument("--case", type=int, help="run this case alone and print everything")
    ap.add_argument("--keep", type=Path, help="with --case: keep the volume, prior and truth in this folder")
    ap.add_argument("--json", type=Path, help="write every case's result to this JSON file")
    args = ap.parse_args(argv)
    if not args.geometry.exists():
        print(f"{args.geometry}: missing; build it: chic-design build designs/zframe.yaml", file=sys.stderr)
        return 2
    if args.case is not None:
        r = run_case(args.case, args.seed, args.geometry, args.keep)
        print(json.dumps(r, indent=2))
        return 0
    results = []
    t0 = time.process_time()
    for i in range(args.cases):
        r = run_case(i, args.seed, args.geometry)
        results.append(r)
        good = r["prior"] == "ok" or (r["prior"] == "refused" and r["usable"] < 3)
        flag = "" if good and r["noprior"] in ("ok", "refused") else "  <--"
        print(f"case {i:4d} {','.join(r['stresses']) or '-':<40} tilt {r['tilt']:4.1f} {r['format']:<6} "
              f"usable {r['usable']:2d}/{r['shape'][0]:<3d} "
              f"prior: {r['prior']:<7} {r['prior_detail'][:90]!r} | no prior: {r['noprior']:<7} "
              f"{r['noprior_detail'][:60]!r} cpu {r['prior_cpu_s']:.1f}+{r['noprior_cpu_s']:.1f} s{flag}", flush=True)
        if r["traceback"]:
            print(r["traceback"], flush=True)
    print(table(results))
    print(f"cpu {time.process_time() - t0:.0f} s for {args.cases} cases")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    bad = sum(r[k] in ("false", "crash") for r in results for k in ("prior", "noprior"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
