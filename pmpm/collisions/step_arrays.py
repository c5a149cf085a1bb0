"""A contact step's arithmetic over whole arrays, compiled (numba): the bodies' working copy
(``solver.Bodies``), the contact record's merge of its pairs and wall contacts (``search``), and in
a dense step the targets the sweeps drive each contact to and the move of every body to the step's
end (``dense`` says what they are). Each does in one pass what a dozen or two whole-array numpy
operations did, with the same floating-point operations in the same order (the same bits): a
step's fixed cost in calls does not shrink with the particles a rank holds, so on several ranks it
weighed more than its share (docs/collisions.md, "Speed on 2 ranks").
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .impulses import roll_resistance
from .settings import CONTACT_TOL

STICKING_SLACK = 1.0 - 1e-9   # a tangential impulse this close to the cone's edge is sliding


@njit(cache=True)
def working_copy(x, v, omega, radius, mass, movable, stays, prescribed):
    """The arrays of ``solver.Bodies`` for particles (n rows) and the world (row n): x, v, ω (v 0
    where the particle ``stays``: fixed or deposited), 1/m and 1/I (0 unless ``movable``), r, free,
    driven (``prescribed`` and moving)."""
    n = len(radius)
    x_all, v_all, w_all = np.zeros((n + 1, 3)), np.zeros((n + 1, 3)), np.zeros((n + 1, 3))
    inv_m, inv_i, r_all = np.zeros(n + 1), np.zeros(n + 1), np.zeros(n + 1)
    free, driven = np.zeros(n + 1, np.bool_), np.zeros(n + 1, np.bool_)
    for i in range(n):
        moving = False
        for d in range(3):
            x_all[i, d], w_all[i, d] = x[i, d], omega[i, d]
            v_all[i, d] = 0.0 if stays[i] else v[i, d]
            moving = moving or v_all[i, d] != 0.0
        if movable[i]:
            inv_m[i] = 1.0 / mass[i]
        arm = max(radius[i], 1e-300)
        inv_i[i] = 2.5 * inv_m[i] / (arm * arm)   # 1/I, I = 2/5 m r²
        r_all[i], free[i], driven[i] = radius[i], movable[i], prescribed[i] and moving
    return x_all, v_all, w_all, inv_m, inv_i, r_all, free, driven


@njit(cache=True)
def targets(rows, first, second, normal, gap, time, restitution, u_wall, r_first, r_second, v, w, rest_speed, dt):
    """Per contact of ``rows`` (the others left False and 0): whether it touches, whether it is an
    impact, the normal velocity it is driven to (m/s), and the time inside the step its impact
    happens (s; 0 for a touching one and for the others); and the largest closing speed at the
    step's start over ``rows`` (m/s, its size)."""
    m = len(first)
    target, hit_time = np.zeros(m), np.zeros(m)
    touching, hits = np.zeros(m, np.bool_), np.zeros(m, np.bool_)
    largest = 0.0
    for c in rows:
        i, j = first[c], second[c]
        s0 = r_first[c] * w[i, 0] + r_second[c] * w[j, 0]
        s1 = r_first[c] * w[i, 1] + r_second[c] * w[j, 1]
        s2 = r_first[c] * w[i, 2] + r_second[c] * w[j, 2]
        n0, n1, n2 = normal[c, 0], normal[c, 1], normal[c, 2]
        u0 = v[i, 0] - v[j, 0] - u_wall[c, 0] - (s1 * n2 - s2 * n1)
        u1 = v[i, 1] - v[j, 1] - u_wall[c, 1] - (s2 * n0 - s0 * n2)
        u2 = v[i, 2] - v[j, 2] - u_wall[c, 2] - (s0 * n1 - s1 * n0)
        speed = -(u0 * n0 + u1 * n1 + u2 * n2)
        largest = max(largest, abs(speed))
        touching[c] = gap[c] <= CONTACT_TOL * r_first[c]
        hits[c] = speed > rest_speed and (touching[c] or time[c] <= dt)
        target[c] = restitution[c] * speed if hits[c] else -max(gap[c], 0.0) / dt
        if hits[c] and not touching[c] and np.isfinite(time[c]):
            hit_time[c] = time[c]
    return touching, hits, target, hit_time, largest


@njit(cache=True)
def change_times(rows, first, second, lam_n, lam_t, hit_time, n):
    """Per body (n + 1,): the sizes of its contacts' impulses summed (``weight``), and the same
    weighted by each contact's impact time (``late``): the body's velocity changed at late / weight."""
    weight_first, weight_second = np.zeros(n + 1), np.zeros(n + 1)
    late_first, late_second = np.zeros(n + 1), np.zeros(n + 1)
    for c in rows:
        strength = np.sqrt(lam_n[c] * lam_n[c] + (lam_t[c, 0] * lam_t[c, 0] + lam_t[c, 1] * lam_t[c, 1]
                                                   + lam_t[c, 2] * lam_t[c, 2]))
        weight_first[first[c]] += strength
        weight_second[second[c]] += strength
        late_first[first[c]] += strength * hit_time[c]
        late_second[second[c]] += strength * hit_time[c]
    return weight_first + weight_second, late_first + late_second


@njit(cache=True)
def move_to_end(rows, contacts, lam_n, lam_t, touching, hits, weight, late, bodies, v0, wall_omega, dt):
    """Rolling friction at the sticking wall contacts of ``rows``, then every body moved to the
    step's end: x += v dt − (v − v0) t_change (t_change = late / weight, ``change_times``).
    contacts : (first, triangle, normal, u_wall, μ, μ_r); bodies : (x, v, w, 1/m, 1/I, r).
    Returns the counts of the contacts that pushed: pair impacts, wall impacts, resting."""
    first, triangle, normal, u_wall, mu, mu_r = contacts
    x, v, w, inv_m, inv_i, radius = bodies
    displacement = np.empty_like(v)
    for i in range(len(v)):
        changed_at = late[i] / weight[i] if weight[i] > 0 else 0.0
        for d in range(3):
            displacement[i, d] = -(v[i, d] - v0[i, d]) * changed_at
    rolling = np.empty(len(rows), np.int64)
    count = 0
    pair_impacts, wall_impacts, resting = 0, 0, 0
    for c in rows:
        wall = triangle[c] >= 0
        if lam_n[c] > 0:
            if not hits[c]:
                resting += 1
            elif wall:
                wall_impacts += 1
            else:
                pair_impacts += 1
        if wall and mu_r[c] > 0 and touching[c] and lam_n[c] > 0:
            size = np.sqrt(lam_t[c, 0] * lam_t[c, 0] + lam_t[c, 1] * lam_t[c, 1] + lam_t[c, 2] * lam_t[c, 2])
            if size < mu[c] * lam_n[c] * STICKING_SLACK:
                rolling[count] = c
                count += 1
    roll_resistance(rolling[:count], first, triangle, normal, u_wall, wall_omega, lam_n, mu_r, inv_m, inv_i, radius,
                    v, w)
    for i in range(len(v)):
        for d in range(3):
            x[i, d] += v[i, d] * dt + displacement[i, d]
    return pair_impacts, wall_impacts, resting


@njit(cache=True)
def merged_record(pair_rows, pairs, pair_normal, pair_gap, pair_time, restitution, friction, wall_rows, wall_particle,
                  wall_triangle, wall_normal, wall_gap, wall_face, wall_time, wall_velocity, wall_restitution,
                  wall_friction, wall_rolling_friction, world):
    """The arrays of a ``record.ContactRecord`` (in its field order): the particle pairs
    ``pair_rows`` of the narrow phase's (``pairs`` (k, 2) sorted, with their normal, gap, time;
    the particles' ``restitution`` and ``friction``) and its wall contacts ``wall_rows`` (sorted by
    particle, then triangle; coefficients per triangle), merged so that each wall contact follows
    the pairs of its particle (``world``: the row of the world body, a wall contact's second)."""
    k, w = len(pair_rows), len(wall_rows)
    m = k + w
    first, second, triangle = np.empty(m, np.int64), np.empty(m, np.int64), np.empty(m, np.int64)
    normal, gap, face, time = np.empty((m, 3)), np.empty(m), np.empty(m, np.bool_), np.empty(m)
    velocity, e, mu, mu_r = np.zeros((m, 3)), np.empty(m), np.empty(m), np.zeros(m)
    i, j = 0, 0
    for out in range(m):
        if j < w and (i == k or wall_particle[wall_rows[j]] < pairs[pair_rows[i], 0]):
            c = wall_rows[j]
            first[out], second[out], triangle[out] = wall_particle[c], world, wall_triangle[c]
            for d in range(3):
                normal[out, d], velocity[out, d] = wall_normal[c, d], wall_velocity[c, d]
            gap[out], face[out], time[out] = wall_gap[c], wall_face[c], wall_time[c]
            t = wall_triangle[c]
            e[out], mu[out], mu_r[out] = wall_restitution[t], wall_friction[t], wall_rolling_friction[t]
            j += 1
        else:
            c = pair_rows[i]
            first[out], second[out], triangle[out] = pairs[c, 0], pairs[c, 1], -1
            for d in range(3):
                normal[out, d] = pair_normal[c, d]
            gap[out], face[out], time[out] = pair_gap[c], True, pair_time[c]
            e[out], mu[out] = restitution, friction
            i += 1
    return first, second, triangle, normal, gap, face, time, velocity, e, mu, mu_r
