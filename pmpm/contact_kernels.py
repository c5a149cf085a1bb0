"""Compiled (numba) kernels of the contacts: projected Gauss–Seidel sweeps over sphere contacts,
and the pair filter of the dense step's contact search.

Projected Gauss–Seidel takes one contact at a time, in the order given: the normal impulse λ_n
is clamped to >= 0 and the tangential impulse λ_t to the Coulomb cone |λ_t| <= μ λ_n, both on
the impulses accumulated so far (so impulses already applied are the warm start), and the change
is applied to the two bodies at once, so the next contact sees it. Each update only removes
energy. Used by the dense step and by the small coupled sets of resting contacts
(``pmpm.collisions``).

Bodies are spheres: the arms from the centres to the contact point are −r_i n and r_j n, so the
contact-point velocity of i relative to j is u = v_i − v_j − u_wall − (r_i ω_i + r_j ω_j) × n and an
impulse J on i (−J on j) changes ω_i by −r_i (n × J)/I_i and ω_j by −r_j (n × J)/I_j. A wall, a
fixed or a deposited particle is a body with zero inverse mass and inertia.

The kernels are compiled on their first call and cached next to this file (numba writes its
cache files under a temporary name and renames them, so ranks that compile at once do not clash);
numba itself is imported then too (~0.3 s), so runs without collisions never load it. Compiled
code is deterministic: the same contacts in the same order give the same bits on every rank,
which the replicated particle update needs.
"""
from __future__ import annotations

from functools import cache

import numpy as np


@cache
def compiled(function):
    """``function`` compiled by numba (nopython, cached on disk), on first use."""
    from numba import njit
    return njit(cache=True)(function)


def projected_gauss_seidel(i, j, normal, r_i, r_j, u_wall, target, mu, inv_mass, inv_inertia, v, omega,
                           lam_n, lam_t, sweeps: int, tol: float) -> int:
    """Sweep over the contacts until no contact changes the velocities by more than ``tol`` (m/s)
    or ``sweeps`` sweeps are done; returns the sweeps made.

    Parameters
    ----------
    i, j : (m,) int
        The contact's bodies (rows of ``v``); the normal points towards i.
    normal : (m, 3) unit normals; r_i, r_j : (m,) arm lengths (m), 0 for a wall.
    u_wall : (m, 3) wall surface velocity at the contact point (m/s), 0 between particles.
    target : (m,) normal relative velocity (m/s) each contact is driven to (>= where λ_n = 0).
    mu : (m,) Coulomb friction coefficient.
    inv_mass, inv_inertia : (nb,) 1/m (1/kg) and 1/I (1/(kg m²)) per body; 0 for infinite mass.
    v, omega : (nb, 3) float64, C-contiguous, updated in place (m/s, rad/s).
    lam_n : (m,) float64 and lam_t : (m, 3) float64, C-contiguous, the impulses (N s) on i
        accumulated so far (already applied to v and ω), updated in place.
    """
    for name, array in (("v", v), ("omega", omega), ("lam_n", lam_n), ("lam_t", lam_t)):
        if array.dtype != np.float64 or not array.flags.c_contiguous:
            raise TypeError(f"{name} must be a C-contiguous float64 array (it is updated in place)")
    as_int = lambda a: np.ascontiguousarray(a, np.int64)
    as_float = lambda a: np.ascontiguousarray(a, np.float64)
    sweep = compiled(_sweeps)
    return int(sweep(as_int(i), as_int(j), as_float(normal), as_float(r_i), as_float(r_j), as_float(u_wall),
                     as_float(target), as_float(mu), as_float(inv_mass), as_float(inv_inertia), v, omega,
                     lam_n, lam_t, int(sweeps), float(tol)))


def _sweeps(i, j, normal, r_i, r_j, u_wall, target, mu, inv_mass, inv_inertia, v, omega, lam_n, lam_t,
            sweeps, tol):  # pragma: no cover - compiled
    m = len(i)
    inv_kn = np.empty(m)
    inv_kt = np.empty(m)
    for c in range(m):
        a, b = i[c], j[c]
        k_n = inv_mass[a] + inv_mass[b]
        k_t = k_n + inv_inertia[a] * r_i[c] * r_i[c] + inv_inertia[b] * r_j[c] * r_j[c]
        # two bodies of infinite mass (a particle deposited this step on a wall): nothing moves
        inv_kn[c] = 1.0 / k_n if k_n > 0 else 0.0
        inv_kt[c] = 1.0 / k_t if k_t > 0 else 0.0
    done = 0
    for sweep in range(sweeps):
        largest = 0.0
        for c in range(m):
            a, b = i[c], j[c]
            n0, n1, n2 = normal[c, 0], normal[c, 1], normal[c, 2]
            ra, rb = r_i[c], r_j[c]
            # u = v_a − v_b − u_wall − (r_a ω_a + r_b ω_b) × n
            s0 = ra * omega[a, 0] + rb * omega[b, 0]
            s1 = ra * omega[a, 1] + rb * omega[b, 1]
            s2 = ra * omega[a, 2] + rb * omega[b, 2]
            u0 = v[a, 0] - v[b, 0] - u_wall[c, 0] - (s1 * n2 - s2 * n1)
            u1 = v[a, 1] - v[b, 1] - u_wall[c, 1] - (s2 * n0 - s0 * n2)
            u2 = v[a, 2] - v[b, 2] - u_wall[c, 2] - (s0 * n1 - s1 * n0)
            u_n = u0 * n0 + u1 * n1 + u2 * n2
            old_n = lam_n[c]
            new_n = max(old_n + (target[c] - u_n) * inv_kn[c], 0.0)
            t0 = lam_t[c, 0] - (u0 - u_n * n0) * inv_kt[c]
            t1 = lam_t[c, 1] - (u1 - u_n * n1) * inv_kt[c]
            t2 = lam_t[c, 2] - (u2 - u_n * n2) * inv_kt[c]
            size = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            limit = mu[c] * new_n
            if size > limit:  # outside the cone: slide, at μ λ_n
                scale = limit / size
                t0, t1, t2 = t0 * scale, t1 * scale, t2 * scale
            d_n = new_n - old_n
            J0 = d_n * n0 + t0 - lam_t[c, 0]
            J1 = d_n * n1 + t1 - lam_t[c, 1]
            J2 = d_n * n2 + t2 - lam_t[c, 2]
            lam_n[c] = new_n
            lam_t[c, 0], lam_t[c, 1], lam_t[c, 2] = t0, t1, t2
            # n × J, for the spins
            c0, c1, c2 = n1 * J2 - n2 * J1, n2 * J0 - n0 * J2, n0 * J1 - n1 * J0
            ma, mb = inv_mass[a], inv_mass[b]
            wa, wb = inv_inertia[a] * ra, inv_inertia[b] * rb
            v[a, 0] += ma * J0
            v[a, 1] += ma * J1
            v[a, 2] += ma * J2
            v[b, 0] -= mb * J0
            v[b, 1] -= mb * J1
            v[b, 2] -= mb * J2
            omega[a, 0] -= wa * c0
            omega[a, 1] -= wa * c1
            omega[a, 2] -= wa * c2
            omega[b, 0] -= wb * c0
            omega[b, 1] -= wb * c1
            omega[b, 2] -= wb * c2
            change = np.sqrt(J0 * J0 + J1 * J1 + J2 * J2) * (ma + mb)
            if change > largest:
                largest = change
        done = sweep + 1
        if largest <= tol:
            break
    return done


def closing_pairs(pairs, x, v, radius, free, reach, horizon, tol) -> np.ndarray:
    """(k,) bool over candidate ``pairs`` (k, 2) of particles: at least one ``free``, centres
    apart, and a gap g = |x_i − x_j| − r_i − r_j with g <= ``reach`` + tol (r_i + r_j) (m) and
    g <= |v_i − v_j| ``horizon`` + tol r_i: it can close within ``horizon`` (s) at the centres'
    relative speed. x, v (n, 3), radius (n,), free (n,) bool."""
    as_float = lambda a: np.ascontiguousarray(a, np.float64)
    return compiled(_closing_pairs)(np.ascontiguousarray(pairs, np.int64), as_float(x), as_float(v), as_float(radius),
                                    np.ascontiguousarray(free, np.bool_), float(reach), float(horizon), float(tol))


def _closing_pairs(pairs, x, v, radius, free, reach, horizon, tol):  # pragma: no cover - compiled
    keep = np.zeros(len(pairs), np.bool_)
    for c in range(len(pairs)):
        a, b = pairs[c, 0], pairs[c, 1]
        if not (free[a] or free[b]):
            continue
        d0, d1, d2 = x[a, 0] - x[b, 0], x[a, 1] - x[b, 1], x[a, 2] - x[b, 2]
        dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        gap = dist - (radius[a] + radius[b])
        if dist <= 0 or gap > tol * (radius[a] + radius[b]) + reach:
            continue
        w0, w1, w2 = v[a, 0] - v[b, 0], v[a, 1] - v[b, 1], v[a, 2] - v[b, 2]
        keep[c] = gap <= np.sqrt(w0 * w0 + w1 * w1 + w2 * w2) * horizon + tol * radius[a]
    return keep
