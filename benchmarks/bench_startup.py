"""Start-up cost of a one-shot ``chic-register solve`` of one DICOM slice, against ``import numpy, pydicom``.

    .venv/bin/python benchmarks/bench_startup.py [--runs 10] [--volume FILE --volume-geometry DESIGN --prior P]

Builds nothing: writes the ``neuro`` geometry and one simulated DICOM slice
to a temporary folder, compiles the package's bytecode once (as an installed
package has it), then alternates fresh processes of
``python -c 'import numpy, pydicom'`` and ``python -m chic_register.cli.main solve
slice.dcm --geometry geometry.yaml`` and reports the median wall and CPU time
(user + system of the child) of each and their ratio, with the machine load
(the target: solve <= 1.3 x the bare imports). With ``--volume``, a one-shot
solve of that volume file (the geometry built from ``--volume-geometry``, a
design YAML, and ``--prior``) joins the alternation, reported against the
one-slice solve (the target: <= 1.5 x).
"""

from __future__ import annotations

import argparse
import compileall
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(cmd: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds of one child process."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--volume", help="also time a one-shot solve of this volume file")
    ap.add_argument("--volume-geometry", default=str(ROOT / "designs" / "zframe.yaml"),
                    help="the volume's design YAML (default designs/zframe.yaml)")
    ap.add_argument("--prior", default=None, help="the volume solve's --prior (e.g. RAS)")
    args = ap.parse_args()
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec
    from chic_register.imaging.simulate import simulate_slice, write_simulated
    from chic_register.model.geometry import write_geometry

    compileall.compile_dir(str(ROOT / "chic_register"), quiet=1)
    with tempfile.TemporaryDirectory() as tmp:
        geom = geometry_of(load_spec(ROOT / "designs" / "neuro.yaml"))
        gpath = write_geometry(geom, Path(tmp) / "geometry.yaml")
        dcm = Path(tmp) / "slice.dcm"
        write_simulated(simulate_slice(geom, 22, 20, 30, 15, noise="rician", snr=20, rng=3), dcm)
        base_cmd = [sys.executable, "-c", "import numpy, pydicom"]
        solve_cmd = [sys.executable, "-m", "chic_register.cli.main", "solve", str(dcm), "--geometry", str(gpath)]
        _run(solve_cmd)  # warm the file cache
        volume_cmd = None
        if args.volume:
            vpath = write_geometry(geometry_of(load_spec(args.volume_geometry)), Path(tmp) / "volume-geometry.yaml")
            volume_cmd = [sys.executable, "-m", "chic_register.cli.main", "solve", str(args.volume), "--geometry",
                          str(vpath), *(["--prior", args.prior] if args.prior else [])]
            _run(volume_cmd)
        base, solve, volume = [], [], []
        load0 = os.getloadavg()[0]
        for _ in range(args.runs):
            base.append(_run(base_cmd))
            solve.append(_run(solve_cmd))
            if volume_cmd:
                volume.append(_run(volume_cmd))
    bw, bc = (statistics.median(v[i] for v in base) for i in (0, 1))
    sw, sc = (statistics.median(v[i] for v in solve) for i in (0, 1))
    print(f"import numpy, pydicom: median wall {bw * 1e3:.0f} ms, CPU {bc * 1e3:.0f} ms ({args.runs} runs)")
    print(f"chic-register solve (one DICOM slice): median wall {sw * 1e3:.0f} ms, CPU {sc * 1e3:.0f} ms")
    print(f"ratio: wall {sw / bw:.2f}, CPU {sc / bc:.2f} (target <= 1.3 -> "
          f"{'met' if sc / bc <= 1.3 else 'MISSED'} on CPU, {'met' if sw / bw <= 1.3 else 'MISSED'} on wall); "
          f"load average {load0:.2f} before, {os.getloadavg()[0]:.2f} after, on {os.cpu_count()} cores")
    if volume:
        vw, vc = (statistics.median(v[i] for v in volume) for i in (0, 1))
        print(f"chic-register solve {Path(args.volume).name}: median wall {vw * 1e3:.0f} ms, CPU {vc * 1e3:.0f} ms; "
              f"against the one-slice solve: wall {vw / sw:.2f}, CPU {vc / sc:.2f} (target <= 1.5 -> "
              f"{'met' if vw / sw <= 1.5 else 'MISSED'} on wall)")


if __name__ == "__main__":
    main()
