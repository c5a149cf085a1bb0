"""The broad search for particle pairs, compiled (numba): a cell list.

The centres are sorted into cubic cells of side 2 (r_max + the largest reach) (a counting sort),
so every pair closer than that lies in the same or in neighbouring cells; each particle then
checks the 27 cells around its own. O(n) for a pack (a few particles per cell). Cells are grown when the
particles are spread thinly (at most 8 per particle), so a gas in a large domain costs no more
than its particles.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .settings import CONTACT_TOL


@njit(cache=True)
def close_pairs(x, radius, reach, chosen):
    """(k, 2) int64 pairs i < j, sorted, with |x_i − x_j| <= (r_i + r_j)(1 + 1e-6) + reach_i +
    reach_j (m) and ``chosen[i]`` or ``chosen[j]``. x (n, 3), radius (n,), reach (n,) m, chosen
    (n,) bool."""
    n = len(radius)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    cell = 2.0 * radius.max() * (1.0 + CONTACT_TOL) + 2.0 * reach.max()
    lower = np.empty(3)
    dims = np.empty(3, np.int64)
    for d in range(3):
        lower[d] = x[:, d].min()
    while True:  # cells no finer than 8 per particle
        total = 1
        for d in range(3):
            dims[d] = int((x[:, d].max() - lower[d]) / cell) + 1
            total *= dims[d]
        if total <= 8 * n + 27:
            break
        cell *= 2.0
    home = np.empty(n, np.int64)
    start = np.zeros(total + 1, np.int64)
    for i in range(n):
        a = min(int((x[i, 0] - lower[0]) / cell), dims[0] - 1)
        b = min(int((x[i, 1] - lower[1]) / cell), dims[1] - 1)
        c = min(int((x[i, 2] - lower[2]) / cell), dims[2] - 1)
        home[i] = (a * dims[1] + b) * dims[2] + c
        start[home[i] + 1] += 1
    for k in range(total):
        start[k + 1] += start[k]
    members = np.empty(n, np.int64)
    fill = start[:total].copy()
    for i in range(n):  # ascending within each cell
        members[fill[home[i]]] = i
        fill[home[i]] += 1
    capacity = 8 * n + 16
    found = np.empty((capacity, 2), np.int64)
    count = 0
    for i in range(n):
        h = home[i]
        a, b, c = h // (dims[1] * dims[2]), (h // dims[2]) % dims[1], h % dims[2]
        begin = count
        for da in range(max(a - 1, 0), min(a + 2, dims[0])):
            for db in range(max(b - 1, 0), min(b + 2, dims[1])):
                for dc in range(max(c - 1, 0), min(c + 2, dims[2])):
                    k = (da * dims[1] + db) * dims[2] + dc
                    for at in range(start[k], start[k + 1]):
                        j = members[at]
                        if j <= i or not (chosen[i] or chosen[j]):
                            continue
                        d0, d1, d2 = x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]
                        limit = (radius[i] + radius[j]) * (1.0 + CONTACT_TOL) + reach[i] + reach[j]
                        if d0 * d0 + d1 * d1 + d2 * d2 > limit * limit:
                            continue
                        if count == capacity:
                            capacity *= 2
                            grown = np.empty((capacity, 2), np.int64)
                            grown[:count] = found[:count]
                            found = grown
                        found[count, 0], found[count, 1] = i, j
                        count += 1
        for at in range(begin + 1, count):  # the few partners of i in order (insertion, in place)
            j = found[at, 1]
            back = at - 1
            while back >= begin and found[back, 1] > j:
                found[back + 1, 1] = found[back, 1]
                back -= 1
            found[back + 1, 1] = j
    return found[:count].copy()
