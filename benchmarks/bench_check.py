"""Benchmark of ``chic-design check``: wall time of the feasibility checks (target < 2 s for neuro).

Run: ``.venv/bin/python benchmarks/bench_check.py [SPEC ...] [--runs N]``. Prints, per
spec, the median and min over N in-process runs of ``family_of(spec).check``, and
the median wall and CPU (user + sys) time of the full CLI in a fresh
interpreter (imports included). On a shared machine the CPU time is the
steadier figure.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chic_design.families import family_of  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("specs", nargs="*", default=[str(ROOT / "designs/neuro.yaml")])
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    for path in args.specs:
        spec = load_spec(path)
        times = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            report = family_of(spec).check(spec)
            times.append(time.perf_counter() - t0)
        cli, cpu = [], []
        for _ in range(args.runs):
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "chic_design.cli", "check", path], cwd=ROOT,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
            cli.append(time.perf_counter() - t0)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu.append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
        print(f"{path}: check median {statistics.median(times):.3f} s (min {min(times):.3f} s), "
              f"CLI median {statistics.median(cli):.3f} s wall, {statistics.median(cpu):.3f} s CPU "
              f"over {args.runs} runs; "
              f"{len(report.tilt_limits)} depths, feasible={report.feasible}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
