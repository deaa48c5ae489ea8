"""Minimum-cost assignment of rows to columns (the Hungarian matching of Mask2Former-style losses).

A cost matrix of queries x ground-truth masks is small (at most a few hundred
by a few dozen) and is solved once per decoder layer and sample, so a plain
shortest-augmenting-path algorithm (Jonker-Volgenant's, O(n^2 m)) in NumPy is
enough; it gives the same optimum as scipy.optimize.linear_sum_assignment,
which this project does not depend on.
"""

from __future__ import annotations

import numpy as np


def min_cost_assignment(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cost (R, C), finite -> (rows, cols) of an assignment of min(R, C) pairs with the least total cost, each row
    and each column used at most once; sorted by row, as scipy's linear_sum_assignment returns them."""
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2:
        raise ValueError(f"cost must be 2-D, got shape {cost.shape}")
    if not np.isfinite(cost).all():
        raise ValueError("cost must be finite")
    transposed = cost.shape[0] > cost.shape[1]
    a = cost.T if transposed else cost  # n rows <= m columns: every row is assigned
    n, m = a.shape
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    u, v = np.zeros(n + 1), np.zeros(m + 1)  # potentials; index 0 is the virtual start
    owner = np.zeros(m + 1, dtype=np.int64)  # owner[j]: row (1-based) holding column j, 0: free
    for row in range(1, n + 1):
        owner[0] = row
        j0 = 0
        slack = np.full(m + 1, np.inf)
        prev = np.zeros(m + 1, dtype=np.int64)
        used = np.zeros(m + 1, dtype=bool)
        while True:  # grow a shortest-path tree from `row` until it reaches a free column
            used[j0] = True
            i0 = owner[j0]
            free = ~used[1:]
            reduced = a[i0 - 1] - u[i0] - v[1:]  # (m,)
            better = free & (reduced < slack[1:])
            slack[1:][better] = reduced[better]
            prev[1:][better] = j0
            candidates = np.where(free, slack[1:], np.inf)
            j1 = int(np.argmin(candidates)) + 1
            delta = candidates[j1 - 1]
            u[owner[used]] += delta
            v[used] -= delta
            slack[1:][free] -= delta
            j0 = j1
            if owner[j0] == 0:
                break
        while j0:  # flip the path
            j1 = prev[j0]
            owner[j0] = owner[j1]
            j0 = j1
    cols = np.nonzero(owner[1:])[0]
    rows = owner[1:][cols] - 1
    if transposed:
        rows, cols = cols, rows
    order = np.argsort(rows)
    return rows[order].astype(np.int64), cols[order].astype(np.int64)
