"""Fast start: what a one-shot solve imports, and the small solvers that replaced scipy.optimize on that path."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.model.tubes import HelixTube
from chic_register.precision.uncertainty import normal_quantile
from chic_register.util.matching import gated_matching, hungarian
from chic_register.util.roots import bracketed_root

SLOW_IMPORTS = ("scipy.optimize", "SimpleITK", "matplotlib")


def _modules_after(code: str) -> set[str]:
    """The modules a fresh interpreter holds after running ``code``."""
    probe = code + "\nimport json, sys\nprint(json.dumps(sorted(sys.modules)))\n"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=120)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_geometry_import_does_not_pull_in_scipy_optimize():
    mods = _modules_after("import chic_register.model.geometry")
    assert "chic_register.model.geometry" in mods and "scipy.optimize" not in mods


def test_one_shot_dicom_solve_imports_only_what_a_slice_needs(tmp_path, neuro_geometry, neuro_geometry_file):
    sim = simulate_slice(neuro_geometry, 22.0, 20.0, 30.0, 15.0, noise="rician", snr=20, rng=3)
    dcm = tmp_path / "slice.dcm"
    write_simulated(sim, dcm)
    code = ("import sys\nfrom chic_register.cli.main import main\n"
            f"rc = main(['solve', {str(dcm)!r}, '--geometry', {str(neuro_geometry_file)!r}, '--json'])\n"
            "assert rc == 0, rc")
    mods = _modules_after(code)
    assert "chic_register.pipeline.register" in mods and "pydicom" in mods  # it did solve, from the DICOM
    assert not [m for m in mods if m.split(".")[0] in ("SimpleITK", "matplotlib", "pyigtl")
                or m.startswith(("scipy.optimize", "scipy.ndimage", "scipy.special"))
                or m == "numpy.ma" or m.startswith("numpy.ma.")  # np.median / np.unique import it: ~40 ms
                or m in ("statistics", "fractions", "chic_register.io.volumes", "chic_register.pipeline.volume")]  # NormalDist: ~4 ms (uncertainty.normal_quantile instead)
    # a sharp slice needs neither the bound's renderer (pose_params holds the covariance's convention) nor the
    # blurred pixel fit (wide_blobs decides it is not needed)
    assert "chic_register.precision.crlb" not in mods and "chic_register.fit.blurred" not in mods


def test_normal_quantile_matches_the_standard_library():
    from statistics import NormalDist

    for p in (1e-6, 0.01, 0.2, 0.5, 0.8, 0.95, 0.99, 0.999, 1 - 1e-6):
        assert normal_quantile(p) == pytest.approx(NormalDist().inv_cdf(p), abs=1e-9)
    assert normal_quantile(0.975) == pytest.approx(1.959964, abs=1e-6)  # the textbook two-sided 95 %
    for bad in (0.0, 1.0, -0.1, float("nan")):
        with pytest.raises(ValueError):
            normal_quantile(bad)


def test_bracketed_root_matches_known_roots_and_keeps_to_the_bracket():
    rng = np.random.default_rng(4)
    for _ in range(200):
        root = float(rng.uniform(-1.5, 1.5))
        k = float(rng.uniform(0.2, 5.0))
        f = lambda x, root=root, k=k: math.tanh(k * (x - root)) + 0.3 * (x - root) ** 3  # noqa: E731
        x = bracketed_root(f, -2.0, 2.0, f(-2.0), f(2.0), xtol=1e-12)
        assert abs(x - root) < 1e-10
    # a flat-then-steep function (regula falsi's worst case) and a triple root still converge
    assert bracketed_root(lambda x: x**9 - 1e-9, 0.0, 1.0, -1e-9, 1.0) == pytest.approx(0.1, abs=1e-9)
    assert bracketed_root(lambda x: (x - 0.7) ** 3, 0.0, 1.0, -0.343, 0.027) == pytest.approx(0.7, abs=1e-9)
    with pytest.raises(ValueError, match="bracket"):
        bracketed_root(lambda x: x * x + 1, -1.0, 1.0, 2.0, 2.0)


def test_helix_plane_crossings_are_roots_to_machine_precision():
    h = HelixTube("H0", "helix", 12.5, 10.0, 1.4, 0.0, 50.0, 3.0)
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = np.array([*rng.uniform(-0.6, 0.6, 2), 1.0])  # up to 40 deg tilt: the plane meets the helix
        n /= np.linalg.norm(n)
        o = np.array([0.0, 0.0, rng.uniform(5, 45)])
        pts = h.intersect_plane(o, n)
        assert len(pts) >= 1
        assert np.all(np.abs((pts - o) @ n) < 1e-9)
        assert np.allclose(np.hypot(pts[:, 0], pts[:, 1]), 12.5)


def test_hungarian_is_optimal_against_brute_force():
    rng = np.random.default_rng(2)
    for _ in range(150):
        n, m = int(rng.integers(1, 6)), int(rng.integers(1, 6))
        cost = rng.uniform(0, 10, (n, m)).round(1)  # ties included
        pairs = hungarian(cost.tolist())
        assert len(pairs) == min(n, m)
        assert len({r for r, _ in pairs}) == len(pairs) == len({c for _, c in pairs})
        if n <= m:
            best = min(sum(cost[i, p[i]] for i in range(n)) for p in itertools.permutations(range(m), n))
        else:
            best = min(sum(cost[p[j], j] for j in range(m)) for p in itertools.permutations(range(n), m))
        assert sum(cost[r, c] for r, c in pairs) == pytest.approx(best)


def test_gated_matching_maximises_allowed_pairs_first():
    # tube 0 could take blob 0 (cheap) or blob 1; tube 1 only blob 0: both must be matched
    cost = np.array([[0.1, 5.0], [1.0, 9.0]])
    allowed = np.array([[True, True], [True, False]])
    r, c = gated_matching(cost, allowed)
    assert dict(zip(r.tolist(), c.tolist())) == {0: 1, 1: 0}
    r, c = gated_matching(cost, np.zeros((2, 2), bool))
    assert r.size == c.size == 0


def test_chi_square_quantile_without_scipy_matches_scipy():
    from scipy.special import gammainc, gammaincinv

    from chic_register.fit.checks import gamma_p, gamma_p_inverse

    for a in (1.5, 3.0, 4.5, 10.0, 27.0, 100.0):
        for p in (0.01, 0.1, 0.5, 0.9):
            assert gamma_p_inverse(a, p) == pytest.approx(float(gammaincinv(a, p)), rel=1e-9)
        for x in (0.2, 1.0, 5.0, 30.0, 150.0):
            assert gamma_p(a, x) == pytest.approx(float(gammainc(a, x)), abs=1e-12)
