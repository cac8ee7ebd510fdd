"""The bracketed root finder (chic_register.util.roots) that replaced scipy.optimize on the solve path."""

from __future__ import annotations

import math

import numpy as np
import pytest

from chic_register.util.roots import bracketed_root


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
