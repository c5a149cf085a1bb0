"""Deposition zones, compiled (numba): a particle that touches a wall of a deposition zone, or a
particle already deposited, sticks there: at rest, of infinite mass from then on, so later
particles deposit on it in turn (a growing deposit)."""
from __future__ import annotations

from numba import njit

from .settings import CONTACT_TOL
from .stats import DEPOSITED


@njit(cache=True)
def deposit(p, v, w, inv_m, inv_i, free, deposited, stats):
    """Particle p sticks where it is."""
    for d in range(3):
        v[p, d] = 0.0
        w[p, d] = 0.0
    inv_m[p] = inv_i[p] = 0.0
    free[p] = False
    deposited[p] = True
    stats[DEPOSITED] += 1


@njit(cache=True)
def deposit_touching(rows, gap, r_first, bodies, contacts, wall_deposition, changed, stats):
    """Deposit the free particles of contacts ``rows`` that touch (gap <= 1e-6 r) a deposition
    wall or a deposited particle; their indices go to ``changed``; returns how many."""
    v, w, inv_m, inv_i, free, deposited = bodies[1], bodies[2], bodies[3], bodies[4], bodies[6], bodies[7]
    first, second, triangle = contacts[0], contacts[1], contacts[2]
    count = 0
    for c in rows:
        if gap[c] > CONTACT_TOL * r_first[c]:
            continue
        a, b, k = first[c], second[c], triangle[c]
        if free[a] and ((k >= 0 and wall_deposition[k]) or (k < 0 and deposited[b])):
            deposit(a, v, w, inv_m, inv_i, free, deposited, stats)
            changed[count] = a
            count += 1
        elif k < 0 and free[b] and deposited[a]:
            deposit(b, v, w, inv_m, inv_i, free, deposited, stats)
            changed[count] = b
            count += 1
    return count
