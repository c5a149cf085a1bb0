"""The broad search for particle pairs, compiled (numba): a cell list.

The centres are sorted into cubic cells of side 2 (r_max + a typical reach) (a counting sort),
so every pair of particles within the typical reach lies in the same or in neighbouring cells;
each particle checks the 27 cells around its own. O(n) for a pack (a few particles per cell).
Where the reach is per particle (a dense step: each particle's travel), the typical reach is the
90th percentile, and the few faster particles ("wide") check as many cells around them as their
own reach needs, for every partner: otherwise a few fast spheres (at a hopper's orifice) would set
the size of every cell, and a slow pack's particles would each check several times as many
neighbours. Where only the pairs with a ``chosen`` particle are wanted (a rank's owned particles
among its ghosts), the others scan nothing: a chosen one lists its partners that are not chosen on
both sides. Cells are grown when
the particles are spread thinly (at most 8 per particle), so a gas in a large domain costs no more
than its particles.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .settings import CONTACT_TOL

TYPICAL = 0.9   # the cells fit the reach of this share of the particles; the rest search wider


@njit(cache=True)
def close_pairs(x, radius, reach, chosen):
    """(k, 2) int64 pairs i < j, sorted, with |x_i − x_j| <= (r_i + r_j)(1 + 1e-6) + reach_i +
    reach_j (m) and ``chosen[i]`` or ``chosen[j]``. x (n, 3), radius (n,), reach (n,) m, chosen
    (n,) bool."""
    n = len(radius)
    if n < 2:
        return np.zeros((0, 2), np.int64)
    typical = np.partition(reach, int(TYPICAL * (n - 1)))[int(TYPICAL * (n - 1))]
    wide = reach > typical
    wide_limit = 2.0 * radius.max() * (1.0 + CONTACT_TOL) + reach.max()   # + a wide particle's own reach
    cell = 2.0 * radius.max() * (1.0 + CONTACT_TOL) + 2.0 * typical
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
    found = np.empty((8 * n + 16, 2), np.int64)
    count = 0
    behind = np.empty((16, 2), np.int64)   # (j, i) with j < i found by i: a wide i, or j not chosen
    late = 0
    for i in range(n):
        if not (chosen[i] or wide[i]):   # (its pairs with chosen ones are listed by them)
            continue
        h = home[i]
        a, b, c = h // (dims[1] * dims[2]), (h // dims[2]) % dims[1], h % dims[2]
        span = int(np.ceil((wide_limit + reach[i]) / cell)) if wide[i] else 1
        begin = count
        for da in range(max(a - span, 0), min(a + span + 1, dims[0])):
            for db in range(max(b - span, 0), min(b + span + 1, dims[1])):
                for dc in range(max(c - span, 0), min(c + span + 1, dims[2])):
                    k = (da * dims[1] + db) * dims[2] + dc
                    for at in range(start[k], start[k + 1]):
                        j = members[at]
                        # a pair with a wide particle is listed by it (two wide ones: the lower)
                        if j == i or not (chosen[i] or chosen[j]) or (wide[j] and j < i):
                            continue
                        if not wide[i] and (wide[j] or (j < i and chosen[j])):
                            continue
                        d0, d1, d2 = x[i, 0] - x[j, 0], x[i, 1] - x[j, 1], x[i, 2] - x[j, 2]
                        limit = (radius[i] + radius[j]) * (1.0 + CONTACT_TOL) + reach[i] + reach[j]
                        if d0 * d0 + d1 * d1 + d2 * d2 > limit * limit:
                            continue
                        if j < i:
                            if late == len(behind):
                                behind = _grown(behind, late)
                            behind[late, 0], behind[late, 1] = j, i
                            late += 1
                            continue
                        if count == len(found):
                            found = _grown(found, count)
                        found[count, 0], found[count, 1] = i, j
                        count += 1
        for at in range(begin + 1, count):  # the few partners of i in order (insertion, in place)
            j = found[at, 1]
            back = at - 1
            while back >= begin and found[back, 1] > j:
                found[back + 1, 1] = found[back, 1]
                back -= 1
            found[back + 1, 1] = j
    if late == 0:
        return found[:count].copy()
    return _merged(found[:count], behind[:late], n)


@njit(cache=True)
def _grown(pairs, count):
    grown = np.empty((2 * len(pairs), 2), np.int64)
    grown[:count] = pairs[:count]
    return grown


@njit(cache=True)
def _merged(pairs, more, n):
    """Two lists of pairs, the first sorted, as one sorted list."""
    key = pairs[:, 0] * n + pairs[:, 1]
    more = more[np.argsort(more[:, 0] * n + more[:, 1])]
    more_key = more[:, 0] * n + more[:, 1]
    out = np.empty((len(pairs) + len(more), 2), np.int64)
    i = k = 0
    for at in range(len(out)):
        if k == len(more) or (i < len(pairs) and key[i] < more_key[k]):
            out[at] = pairs[i]
            i += 1
        else:
            out[at] = more[k]
            k += 1
    return out
