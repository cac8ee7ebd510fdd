"""Does ``check`` agree with ``build``? Random specs: every design check calls feasible must build.

Draws seeded random specs around the repository's designs (sizes, channel
layout, caps, printer limits, protocol), runs ``family_of(spec).check`` on each,
and builds those it calls feasible into a scratch folder. Reports every
disagreement (a feasible design whose build fails) and how many specs were
refused at the door, infeasible, or built. Slow: a build is 10-30 s.

    python benchmarks/check_build_agreement.py --cases 20 --seed 0
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chic_design.build.pipeline import build_design  # noqa: E402
from chic_design.errors import ChicDesignError  # noqa: E402
from chic_design.families import family_of  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402


def random_spec(rng: np.random.Generator, n: int) -> dict:
    """A spec with every size drawn over a wide but plausible range."""
    od = float(rng.uniform(8, 60))
    idia = float(od * rng.uniform(0.2, 0.8))
    wall = (od - idia) / 2
    d = float(wall * rng.uniform(0.2, 0.95))
    return {
        "name": f"agree-{n:03d}",
        "body": {"length": float(rng.uniform(10, 120)), "outer_diameter": round(od, 3),
                 "inner_diameter": round(idia, 3)},
        "channels": {"diameter": round(max(d, 0.2), 3)},
        "helix": {"offset_deg": float(rng.uniform(0, 30))},
        "caps": {"thickness": float(rng.uniform(0.2, 4)), "clearance": float(rng.uniform(0, 0.5)),
                 "skirt_height": float(rng.uniform(0.5, 8)), "skirt_wall": float(rng.uniform(0.2, 4)),
                 "fill_port_diameter": 0.0 if rng.random() < 0.3 else round(max(d, 0.2) * 0.5, 3)},
        "print": {"min_wall": float(rng.uniform(0.1, 1.2))},
        "imaging": {"pixel_size": float(rng.choice([0.3, 0.5, 1.0])), "slice_thickness": float(rng.uniform(0, 3))},
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    counts = {"refused": 0, "infeasible": 0, "built": 0, "DISAGREE": 0}
    with tempfile.TemporaryDirectory() as scratch:
        for n in range(args.cases):
            path = Path(scratch) / f"spec{n:03d}.yaml"
            path.write_text(yaml.safe_dump(random_spec(rng, n)))
            try:
                spec = load_spec(path)
            except ChicDesignError:
                counts["refused"] += 1
                continue
            report = family_of(spec).check(spec)
            if not report.feasible:
                counts["infeasible"] += 1
                print(f"{n:3d} infeasible: {', '.join(sorted({v.code for v in report.violations}))}", flush=True)
                continue
            t0 = time.perf_counter()
            try:
                build_design(path, out_root=Path(scratch) / "exports", progress=False, pictures_in_worker=False)
                counts["built"] += 1
                print(f"{n:3d} feasible and built in {time.perf_counter() - t0:.1f} s", flush=True)
            except Exception as exc:  # noqa: BLE001 - any failure of a feasible design is the finding
                counts["DISAGREE"] += 1
                print(f"{n:3d} DISAGREE: check says feasible, build failed: {type(exc).__name__}: {exc}",
                      flush=True)
                print(path.read_text())
    print(" ".join(f"{k} {v}" for k, v in counts.items()))
    return 1 if counts["DISAGREE"] else 0


if __name__ == "__main__":
    sys.exit(main())
