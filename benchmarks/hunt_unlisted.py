"""False-lock hunt on damage the main hunt does not draw: what a real scanner or a pipeline may do to a slice.

    .venv/bin/python benchmarks/hunt_unlisted.py [--cases 1000] [--seed 7] [--workers 2]

Each case is one of ``benchmarks/hunt.py``'s random slices (its ``noisy``
variant: Rician noise, no other damage), then one of :data:`KINDS` applied
(case ``i`` gets kind ``i % len(KINDS)``): bright specks (hot pixels), motion
blur along rows or columns, Gibbs ringing (k-space cut to 25-60 % along one
axis), a fold-over (wrap-around) strip, quantisation to 4-15 levels, a 2x
bilinear zoom declared with half the spacing (a scanner's interpolated
matrix), NaN pixels, a negative offset (a background subtracted), an
anisotropic blur, a k-space spike (a stripe pattern over the whole image);
and, added later: partial Fourier (55-75 % of k-space along one axis, the
rest zero-filled), an in-plane rotation by a non-right angle with bilinear
resampling (corners zero; the truth turned with it), a sub-pixel shift by
Fourier interpolation (the truth shifted with it), an 8-bit window that
saturates the fluid (and in half the cases clips the background to 0),
inverted contrast, the real part of a complex image under a phase ramp
(signed data), a susceptibility void beside one tube (a dark disc with a
bright crescent), an EPI Nyquist ghost (a half-field copy with alternating
line sign, added coherently), a smooth radial warp (gradient non-linearity:
1-3 % scale error at the image edge; the truth unchanged) and JPEG-like 8x8
block DCT quantisation (:func:`chic_register.studies.damage.unlisted_damage`).
Reports per kind ok / false lock / no_lock / crash (as hunt.py: a false lock
is ``ok`` more than 0.5 mm or 0.5 deg from the truth) and lists the false
locks, crashes and cases over 8 s of wall time. Each worker is limited to
3 GiB of address space, so a runaway allocation is a crash here. Exit status 1 on a crash.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import collections  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import hunt  # noqa: E402

from chic_register.studies.damage import UNLISTED_KINDS, solve_and_judge, unlisted_slice  # noqa: E402

KINDS = UNLISTED_KINDS
MEMORY_LIMIT_BYTES = 3 * 2**30
SLOW_S = 8.0


def _init() -> None:
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))
    hunt._init(None)


def run_case(index: int, seed: int) -> dict:
    """One case: its damage kind, outcome, errors and wall time."""
    kind = KINDS[index % len(KINDS)]
    sl, T_true, case, in_env = unlisted_slice(index, seed, kind, hunt._GEOMS)
    geom = hunt._GEOMS[case.geometry]
    out = {"index": index, "kind": kind, "geometry": case.geometry}
    t0 = time.perf_counter()
    out.update(solve_and_judge(sl, geom, T_true, ndigits=4))
    out.update(in_envelope=bool(in_env), wall_s=round(time.perf_counter() - t0, 3))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    with ProcessPoolExecutor(max_workers=args.workers, initializer=_init) as ex:
        results = list(ex.map(run_case, range(args.cases), [args.seed] * args.cases, chunksize=5))
    counts = collections.defaultdict(collections.Counter)
    for r in results:
        counts[r["kind"]][r["outcome"]] += 1
    print(f"{'damage':>16} {'cases':>6} {'ok':>5} {'false':>6} {'no_lock':>8} {'crash':>6}")
    for kind in KINDS:
        c = counts[kind]
        print(f"{kind:>16} {sum(c.values()):>6} {c['ok']:>5} {c['false_lock']:>6} {c['no_lock']:>8} {c['crash']:>6}")
    total = collections.Counter(r["outcome"] for r in results)
    print(f"cases {len(results)}: ok {total['ok']}, FALSE LOCKS {total['false_lock']}, no_lock {total['no_lock']}, "
          f"crashes {total['crash']}")
    for r in results:
        if r["outcome"] in ("false_lock", "crash") or r["wall_s"] > SLOW_S:
            print({k: v for k, v in r.items() if k != "trace"})
    print(f"wall {time.perf_counter() - t0:.0f} s, {args.workers} workers; load average {load0:.2f} at start, "
          f"{os.getloadavg()[0]:.2f} at end; seed {args.seed}")
    return 1 if total["crash"] else 0


if __name__ == "__main__":
    sys.exit(main())
