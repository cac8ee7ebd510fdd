"""Minimum-cost matching of a small bipartite graph (tubes to blobs), without scipy.optimize.

``scipy.optimize.linear_sum_assignment`` solves this in C, but importing
``scipy.optimize`` costs about a third of a second, several times a whole
registration, on the start-up path of a one-shot ``chic-register solve``.
The solver's graphs are tiny (about ten tubes, a few tens of blobs, each tube
gated to the few blobs near its prediction) and split into independent
components of two or three nodes, so a pure-Python Hungarian method on each
component is as fast as the C routine with its call overhead.
"""

from __future__ import annotations

import numpy as np


def hungarian(cost: list[list[float]]) -> list[tuple[int, int]]:
    """Rows matched to columns ``[(row, col), ...]`` minimising the total cost of a dense matrix (n x m).

    Every row is matched when n <= m (every column when n > m). Shortest
    augmenting paths with potentials, O(n^2 m); meant for a handful of rows.
    """
    n = len(cost)
    m = len(cost[0]) if n else 0
    if n == 0 or m == 0:
        return []
    if n > m:
        return [(r, c) for c, r in hungarian([list(col) for col in zip(*cost)])]
    inf = float("inf")
    u, v = [0.0] * (n + 1), [0.0] * (m + 1)
    p, way = [0] * (m + 1), [0] * (m + 1)  # p[j]: row (1-based) on column j; 0 = free
    for i in range(1, n + 1):
        p[0], j0 = i, 0
        minv, used = [inf] * (m + 1), [False] * (m + 1)
        while True:
            used[j0] = True
            i0, delta, j1 = p[j0], inf, 0
            row, ui = cost[i0 - 1], u[i0]
            for j in range(1, m + 1):
                if not used[j]:
                    cur = row[j - 1] - ui - v[j]
                    if cur < minv[j]:
                        minv[j], way[j] = cur, j0
                    if minv[j] < delta:
                        delta, j1 = minv[j], j
            for j in range(m + 1):
                if used[j]:
                    u[p[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if p[j0] == 0:
                break
        while j0:  # augment along the path
            j1 = way[j0]
            p[j0] = p[j1]
            j0 = j1
    return [(p[j] - 1, j - 1) for j in range(1, m + 1) if p[j]]


def gated_matching(cost: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The most allowed pairs of rows and columns, and among those the least total cost.

    ``cost`` (K, N) float, ``allowed`` (K, N) bool. Returns ``(rows, cols)``
    int arrays of the matched pairs (all allowed), as
    ``linear_sum_assignment`` on ``where(allowed, cost, big)`` keeping the
    allowed pairs would, provided every cost is far below ``1e6``. Solved per
    connected component of the graph of allowed pairs.
    """
    ri, ci = np.nonzero(allowed)
    rows, cols = matched_pairs(allowed.shape[0], allowed.shape[1], ri.tolist(), ci.tolist(), cost[ri, ci].tolist())
    return np.asarray(rows, dtype=int), np.asarray(cols, dtype=int)


def matched_pairs(K: int, N: int, rl: list, cl: list, vals: list) -> tuple[list, list]:
    """:func:`gated_matching` of the allowed pairs given as lists: rows ``rl``, columns ``cl`` (row-major order,
    as ``np.nonzero``'s) and their costs ``vals``, in a K x N graph; the matched rows and columns as lists."""
    if not rl:
        return [], []
    row_deg, col_deg = [0] * K, [0] * N
    for i in rl:
        row_deg[i] += 1
    for j in cl:
        col_deg[j] += 1
    # connected components by union-find over the nodes (rows 0..K-1, columns K..K+N-1); the graphs have a few
    # tens of edges, most of them alone in their row and column: those are components of their own
    parent = list(range(K + N))
    for i, j in zip(rl, cl):
        if row_deg[i] == 1 and col_deg[j] == 1:
            continue
        a, b = i, K + j
        while parent[a] != a:
            a = parent[a]
        while parent[b] != b:
            b = parent[b]
        if a != b:
            parent[a] = b
    comps = {}  # in the order of each component's first edge
    for e, i in enumerate(rl):
        if row_deg[i] == 1 and col_deg[cl[e]] == 1:
            comps[-1 - e] = [e]
            continue
        while parent[i] != i:
            i = parent[i]
        comps.setdefault(i, []).append(e)
    out_r, out_c = [], []
    big = 1e6
    for edges in comps.values():
        if len(edges) == 1:
            out_r.append(rl[edges[0]])
            out_c.append(cl[edges[0]])
            continue
        rows = sorted({rl[e] for e in edges})
        cols = sorted({cl[e] for e in edges})
        if len(rows) == 1 or len(cols) == 1:  # a star: its cheapest edge
            e = min(edges, key=vals.__getitem__)
            out_r.append(rl[e])
            out_c.append(cl[e])
            continue
        r_at, c_at = {r: k for k, r in enumerate(rows)}, {c: k for k, c in enumerate(cols)}
        sub = [[big] * len(cols) for _ in rows]
        for e in edges:
            sub[r_at[rl[e]]][c_at[cl[e]]] = vals[e]
        for a, b in hungarian(sub):
            if sub[a][b] < big:
                out_r.append(rows[a])
                out_c.append(cols[b])
    return out_r, out_c
