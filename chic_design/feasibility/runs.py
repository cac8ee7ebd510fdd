"""Runs of consecutive True samples, as (first, last) sample values: the depth ranges the checks report."""

from __future__ import annotations

import numpy as np


def true_runs(z: np.ndarray, mask: np.ndarray) -> tuple[tuple[float, float], ...]:
    """``(z[first], z[last])`` of every run of True in ``mask`` (``z`` sorted, same length)."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(mask).astype(int), [0]])))
    return tuple((float(z[s]), float(z[e - 1])) for s, e in zip(edges[::2], edges[1::2]))
