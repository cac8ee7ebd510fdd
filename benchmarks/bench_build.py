"""Wall time of a full ``chic-design build`` (default: designs/neuro.yaml), total and per step.

Two figures:

- cold: ``chic-design build SPEC --quiet`` as a fresh process, as a user runs it
  (includes importing build123d/OCCT, about 2.5 s);
- warm: :func:`chic_design.build.pipeline.build_design` called repeatedly in one process
  (the per-step times come from these runs).

Each is the median of ``--runs`` runs. The export goes to a temporary folder.

    .venv/bin/python benchmarks/bench_build.py [SPEC] [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cold_runs(spec: Path, runs: int, out: Path) -> list[float]:
    """Wall times (s) of ``python -m chic_design.cli build SPEC`` in fresh processes."""
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "chic_design.cli", "build", str(spec), "--out", str(out), "--quiet"],
                       check=True, stdout=subprocess.DEVNULL, cwd=ROOT)
        times.append(time.perf_counter() - t0)
    return times


def warm_runs(spec: Path, runs: int, out: Path) -> tuple[list[float], dict[str, list[float]]]:
    """Wall times (s) of ``build_design`` in this process, and per-step times."""
    from chic_design.build.pipeline import build_design

    build_design(spec, out_root=out, progress=False)  # first call: imports and caches
    walls, steps = [], {}
    for _ in range(runs):
        result = build_design(spec, out_root=out, progress=False)
        walls.append(result.wall_s)
        for name, dt in result.timings.items():
            steps.setdefault(name, []).append(dt)
    return walls, steps


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("spec", nargs="?", default=str(ROOT / "designs" / "neuro.yaml"))
    p.add_argument("--runs", type=int, default=3)
    args = p.parse_args(argv)
    spec = Path(args.spec)
    with tempfile.TemporaryDirectory(prefix="bench-build-") as tmp:
        cold = cold_runs(spec, args.runs, Path(tmp) / "cold")
        warm, steps = warm_runs(spec, args.runs, Path(tmp) / "warm")
    print(f"build of {spec.name}, median of {args.runs} runs:")
    print(f"  cold (fresh CLI process): {statistics.median(cold):6.2f} s   runs: "
          + ", ".join(f"{t:.2f}" for t in cold))
    print(f"  warm (build_design)     : {statistics.median(warm):6.2f} s   runs: "
          + ", ".join(f"{t:.2f}" for t in warm))
    print("  per step (warm, median; '(parallel)' steps run in the worker process):")
    for name, ts in steps.items():
        print(f"    {name:32s} {statistics.median(ts):6.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
