"""The real Z-frame scans (tests/data/real) changed the ways scanners and exports change images, through the CLI.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_real_variants.py [--geometry G] [--scan FILE ...]

Each scan is registered as it is (``solve SCAN --geometry G --prior RAS``) and then as a set of variants, each
written with the project's volume writer and solved the same way:

- the same voxels stored otherwise: slices in reverse order, columns flipped, rows and columns swapped, the
  volume's frame turned (an oblique acquisition) or moved: the pose must follow exactly;
- cropped to 160 x 160, padded to 512 x 512;
- intensities x 10 + 500 (float), x 0.01, clipped at 60 % of the maximum (int16), quantised to 8 bits;
- every second slice (4-4.8 mm apart), the odd slices only, 2 x 2 binned pixels;
- more noise (complex Gaussian of 5 % and 10 % of the bright level), a shading of 0.4-1.6 across the columns.

Reports, per variant, ``ok`` with the rotation (deg) and the displacement of the frame centre (mm) from the plain
scan's pose (carried through the variant's own change of frame), and the number of slices used; or the refusal's
reason. A variant of the stored form only should land within a few hundredths; a degraded one may refuse, with its
reason, but an ``ok`` more than 0.5 mm or 0.5 deg from the plain pose is marked ``FAR``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCANS = (ROOT / "tests" / "data" / "real" / "zframe-masked-b.nrrd", ROOT / "tests" / "data" / "real" / "zframe-clinical-3t.nrrd")
CENTRE_F = np.array([0.0, 0.0, 30.0, 1.0])


def solve(path: Path, geometry: str) -> tuple[np.ndarray | None, str]:
    """``(T_scanner_from_fiducial, summary)`` of ``chic-register solve``, or ``(None, the refusal's line)``."""
    out = subprocess.run([sys.executable, "-m", "chic_register.cli.main", "solve", str(path), "--geometry", geometry,
                          "--prior", "RAS", "--json"], capture_output=True, text=True, cwd=ROOT)
    if out.returncode:
        try:
            return None, json.loads(out.stdout)["reason"]
        except (ValueError, KeyError):
            lines = out.stderr.strip().splitlines()
            return None, (lines[-1] if lines else f"exit {out.returncode}").replace("chic-register: ", "")
    doc = json.loads(out.stdout)
    return np.array(doc["T_scanner_from_fiducial"]), f"{doc['n_slices_used']} slices used"


def rotation_deg(A: np.ndarray, B: np.ndarray) -> float:
    R = A[:3, :3].T @ B[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def variants(v):
    """``(name, volume, M)``: each variant and the motion (4x4, scanner mm) that carries the plain scan's pose to the
    variant's (identity where the voxels stay where they were)."""
    nk, nj, ni = v.voxels.shape
    D, o, (si, sj, sk) = v.direction, v.origin_mm, v.spacing_mm
    I4 = np.eye(4)
    rep = dataclasses.replace
    yield "slices reversed", rep(v, voxels=v.voxels[::-1].copy(), origin_mm=o + (nk - 1) * sk * D[:, 2],
                                 direction=np.column_stack([D[:, 0], D[:, 1], -D[:, 2]])), I4
    yield "columns flipped", rep(v, voxels=v.voxels[:, :, ::-1].copy(), origin_mm=o + (ni - 1) * si * D[:, 0],
                                 direction=np.column_stack([-D[:, 0], D[:, 1], D[:, 2]])), I4
    yield "rows and columns swapped", rep(v, voxels=np.ascontiguousarray(v.voxels.transpose(0, 2, 1)[::-1]),
                                          spacing_mm=(sj, si, sk), origin_mm=o + (nk - 1) * sk * D[:, 2],
                                          direction=np.column_stack([D[:, 1], D[:, 0], -D[:, 2]])), I4
    c, s_ = np.cos(np.radians(20.0)), np.sin(np.radians(20.0))
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s_], [0.0, s_, c]])
    M = np.eye(4)
    M[:3, :3] = R
    yield "frame turned (oblique)", rep(v, direction=R @ D, origin_mm=R @ o), M
    shift = np.array([17.3, -8.1, 23.0])
    M = np.eye(4)
    M[:3, 3] = shift
    yield "frame moved", rep(v, origin_mm=o + shift), M
    yield "cropped to 160", rep(v, voxels=v.voxels[:, 48:208, 48:208].copy(),
                                origin_mm=o + 48 * si * D[:, 0] + 48 * sj * D[:, 1]), I4
    yield "padded to 512", rep(v, voxels=np.pad(v.voxels, ((0, 0), (128, 128), (128, 128))),
                               origin_mm=o - 128 * si * D[:, 0] - 128 * sj * D[:, 1]), I4
    x = v.voxels.astype(float)
    yield "x 10 + 500", rep(v, voxels=(x * 10 + 500).astype(np.float32)), I4
    yield "x 0.01", rep(v, voxels=(x * 0.01).astype(np.float32)), I4
    yield "clipped at 60 %", rep(v, voxels=np.clip(x, 0, 0.6 * x.max()).astype(np.int16)), I4
    yield "8 bits", rep(v, voxels=np.round(255 * np.clip(x / x.max(), 0, 1)).astype(np.uint8)), I4
    yield "every second slice", rep(v, voxels=v.voxels[::2].copy(), spacing_mm=(si, sj, 2 * sk),
                                    slice_thickness_mm=v.thickness_mm), I4
    yield "odd slices", rep(v, voxels=v.voxels[1::2].copy(), spacing_mm=(si, sj, 2 * sk), origin_mm=o + sk * D[:, 2],
                            slice_thickness_mm=v.thickness_mm), I4
    b = x[:, :nj // 2 * 2, :ni // 2 * 2].reshape(nk, nj // 2, 2, ni // 2, 2).mean(axis=(2, 4))
    yield "2 x 2 binned", rep(v, voxels=b, spacing_mm=(2 * si, 2 * sj, sk),
                              origin_mm=o + 0.5 * si * D[:, 0] + 0.5 * sj * D[:, 1]), I4
    rng = np.random.default_rng(0)
    bright = float(np.percentile(x, 99.5))
    for share in (0.05, 0.10):
        s = share * bright
        yield f"noise {100 * share:g} %", rep(v, voxels=np.hypot(x + rng.normal(0, s, x.shape), rng.normal(0, s, x.shape))), I4
    shade = 0.4 + 1.2 * np.arange(ni) / ni
    yield "shading 0.4-1.6", rep(v, voxels=x * shade[None, None, :]), I4


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--geometry", default=None, help="the Z-frame's geometry file (default: designs/zframe.yaml's)")
    ap.add_argument("--scan", nargs="+", default=[str(p) for p in SCANS])
    args = ap.parse_args(argv)
    from chic_register.io.volumes import read_volume, write_volume

    with tempfile.TemporaryDirectory() as tmp:
        geometry = args.geometry
        if geometry is None:
            from chic_design.families import geometry_of
            from chic_design.spec import load_spec
            from chic_register.model.geometry import write_geometry

            geometry = str(write_geometry(geometry_of(load_spec(ROOT / "designs" / "zframe.yaml")),
                                          Path(tmp) / "zframe.yaml"))
        far = 0
        for scan in args.scan:
            plain, info = solve(Path(scan), geometry)
            print(f"{Path(scan).name}: {'ok, ' + info if plain is not None else 'refused: ' + info}")
            if plain is None:
                continue
            for n, (name, vol, M) in enumerate(variants(read_volume(scan))):
                path = write_volume(vol, Path(tmp) / f"variant-{n}.nrrd")
                T, info = solve(path, geometry)
                if T is None:
                    print(f"  {name:26s} refused: {info[:150]}")
                    continue
                want = M @ plain
                rot, mm = rotation_deg(want, T), float(np.linalg.norm((want @ CENTRE_F - T @ CENTRE_F)[:3]))
                flag = "FAR" if rot > 0.5 or mm > 0.5 else "ok "
                far += flag == "FAR"
                print(f"  {name:26s} {flag} {rot:6.3f} deg {mm:6.3f} mm from the plain scan's pose; {info}")
        print(f"{far} variants ok more than 0.5 mm or 0.5 deg from the plain scan's pose")
    return 0


if __name__ == "__main__":
    sys.exit(main())
