"""numpy's LAPACK gufuncs without np.linalg's wrappers, for the solver's many small systems.

``np.linalg.solve``, ``eig`` and ``lstsq`` check their arguments, switch the
floating-point error state and wrap the result; on the 2x2 to 6x6 systems the
solver solves thousands of times per slice that costs as much as the LAPACK
call. These call the same gufuncs (a private numpy module: where another
numpy lacks it, each falls back to the public function, with the same
answers). One place, so that the private import is made and guarded once.
"""

from __future__ import annotations

import math

import numpy as np

try:  # a private module: another numpy may lack it (then the public wrappers below)
    from numpy.linalg import _umath_linalg
except ImportError:  # pragma: no cover - the public wrappers
    _umath_linalg = None

GUFUNC_SOLVE1 = getattr(_umath_linalg, "solve1", None)
_EPS = float(np.finfo(float).eps)


def solve(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(A, B)`` of float64 (n, n) matrices (the same LAPACK gufunc, less its wrapper's checks:
    about half the cost), NaNs where it raises LinAlgError for a singular ``A``."""
    if _umath_linalg is None:  # pragma: no cover - a numpy without the private module
        try:
            return np.linalg.solve(A, B)
        except np.linalg.LinAlgError:
            return np.full(B.shape, np.nan)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore", under="ignore"):
        return _umath_linalg.solve(A, B, signature="dd->d")


def solve_vector(H: np.ndarray, g: np.ndarray) -> list[float]:
    """``np.linalg.solve(H, g)`` (float64 (n, n) and (n,)) as a list: the same LAPACK gufunc without the wrapper's
    checks and error-state switch (~5 us a call of ~7); NaNs (and a RuntimeWarning) where np.linalg.solve raises
    LinAlgError for a singular H (the public wrapper, with the same NaNs, where numpy has no such gufunc)."""
    if GUFUNC_SOLVE1 is not None:
        try:
            return GUFUNC_SOLVE1(H, g, signature="dd->d").tolist()
        except TypeError:  # pragma: no cover - a numpy whose private gufunc takes other arguments
            pass
    try:
        return np.linalg.solve(H, g).tolist()
    except np.linalg.LinAlgError:
        return [math.nan] * len(g)


def eig_vectors(M: np.ndarray) -> np.ndarray:
    """The real part of ``np.linalg.eig(M)``'s eigenvectors (columns) of a finite float64 (n, n) matrix, less
    the wrapper (NaNs where it raises for eigenvalues that do not converge)."""
    if _umath_linalg is None:  # pragma: no cover - a numpy without the private module
        try:
            return np.real(np.linalg.eig(M)[1])
        except np.linalg.LinAlgError:
            return np.full(M.shape, np.nan)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore", under="ignore"):
        return _umath_linalg.eig(M, signature="d->DD")[1].real


def lstsq(A: np.ndarray, y: np.ndarray):
    """``(coef, rank)`` of ``np.linalg.lstsq(A, y, rcond=None)`` (A (m, n), y (m,) float): the same LAPACK call
    without the wrapper's checks (a window fit is a few dozen small ones per pose); the wrapper itself (its
    answer, its error) when that call is not there or gives no finite answer."""
    m, n = A.shape
    if _umath_linalg is not None and m > 0 and A.dtype == np.float64 and y.dtype == np.float64:
        try:
            with np.errstate(all="ignore"):
                x, _, rank, _ = _umath_linalg.lstsq(A, y[:, None], _EPS * max(m, n), signature="ddd->ddid")
        except Exception:  # noqa: BLE001 - a numpy whose private call differs: the wrapper below
            x = None
        if x is not None and np.isfinite(x).all():
            return x[:, 0], int(rank)
    coef, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
    return coef, int(rank)
