"""A bracketed scalar root finder (Illinois regula falsi).

Used by the tube objects' plane crossings and the pose checks; a few lines
instead of ``scipy.optimize``, whose import costs a third of a second on the
solver's start-up path.
"""

from __future__ import annotations


def bracketed_root(f, a: float, b: float, fa: float, fb: float, *, xtol: float = 1e-12, max_iter: int = 100) -> float:
    """A root of ``f`` in ``[a, b]`` given ``f(a) = fa`` and ``f(b) = fb`` of opposite signs.

    The Illinois variant of regula falsi (superlinear on smooth functions,
    never leaves the bracket), falling back to bisection when a secant step
    shrinks the bracket too little. Stops when the bracket is below ``xtol``
    (or a value is exactly 0). A few lines instead of ``scipy.optimize``,
    whose import costs a third of a second on the solver's start-up path.
    """
    a, b, fa, fb = float(a), float(b), float(fa), float(fb)
    if fa == 0.0:
        return a
    if fb == 0.0:
        return b
    if fa * fb > 0:
        raise ValueError(f"f({a}) = {fa} and f({b}) = {fb} do not bracket a root")
    side = 0
    for _ in range(max_iter):
        width = abs(b - a)
        if width <= xtol:
            break
        c = (a * fb - b * fa) / (fb - fa)
        if not (min(a, b) < c < max(a, b)):
            c = 0.5 * (a + b)
        fc = float(f(c))
        if fc == 0.0:
            return c
        if fc * fb < 0:  # root between c and b: c replaces a
            a, fa = b, fb
            b, fb = c, fc
            side = 0
        else:  # root between a and c: c replaces b; halve the stale end's value (Illinois)
            b, fb = c, fc
            fa *= 0.5
            side += 1
            if side > 2:  # the same end stuck three times: bisect
                m = 0.5 * (a + b)
                fm = float(f(m))
                if fm == 0.0:
                    return m
                if fm * fb < 0:
                    a, fa = m, fm
                else:
                    b, fb = m, fm
                side = 0
    return b if abs(fb) <= abs(fa) else a
