"""A contact step's arithmetic over whole arrays, compiled (numba): the bodies' working copy
(``solver.Bodies``) and travel, the contact record's merge of its pairs and wall contacts
(``search``), the contact memory's recall and remembering (``record.ContactMemory``), in a dense
step the solve's start, the targets the sweeps drive each contact to and the move of every body
to the step's end (``dense`` says what they are), and the overlaps left to remove
(``solver.remove_overlaps``). Each does in one pass what a dozen or two whole-array
numpy operations did, with the same floating-point operations in the same order (the same bits): a
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
def solve_start(rows, first, second, triangle, warm_n, warm_t, driven, wall_drives, n):
    """The start of a dense solve of the contacts ``rows`` (of m; particles 0..n−1, the world n):
    their impulses, (m,) and (m, 3), the remembered ones ``warm_n``, ``warm_t`` on ``rows`` and 0
    elsewhere; whether any is remembered (not 0); the particles in them (ascending); whether any
    contact is driven (a ``driven`` body, per row, or a triangle that ``wall_drives``)."""
    m = len(first)
    lam_n, lam_t = np.zeros(m), np.zeros((m, 3))
    touched = np.zeros(n + 1, np.bool_)
    remembered, any_driven = False, False
    for c in rows:
        lam_n[c] = warm_n[c]
        for d in range(3):
            lam_t[c, d] = warm_t[c, d]
        remembered = remembered or warm_n[c] != 0.0
        touched[first[c]] = touched[second[c]] = True
        any_driven = any_driven or driven[first[c]] or driven[second[c]] or (
            triangle[c] >= 0 and wall_drives[triangle[c]])
    count = 0
    for i in range(n):
        count += touched[i]
    members, at = np.empty(count, np.int64), 0
    for i in range(n):
        if touched[i]:
            members[at] = i
            at += 1
    return lam_n, lam_t, remembered, members, any_driven


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


@njit(cache=True)
def contact_ids(c, first, second, triangle, ids):
    """(first id, second id) of contact ``c`` (``record.ContactMemory``'s: −1 − triangle for a wall)."""
    return ids[first[c]], (-1 - triangle[c] if triangle[c] >= 0 else ids[second[c]])


@njit(cache=True)
def recalled(first, second, triangle, ids, memory_first, memory_second, memory_normal, memory_tangential):
    """The remembered impulses of a record's contacts, (m,) and (m, 3), 0 where none: each contact's
    ids (``contact_ids``; ``ids`` the particles' by row) looked up in the memory's rows, sorted by
    (first id, second id). A record lists each particle's contacts together, by row (so by id
    where the rows are sorted by id): the memory's rows of the next first id are found walking on
    from the last ones (searched for where the ids go back)."""
    m, k = len(first), len(memory_first)
    normal, tangential = np.zeros(m), np.zeros((m, 3))
    low, high, current = 0, 0, -1     # the memory's rows [low, high) are those of first id ``current``
    for c in range(m):
        first_id, second_id = contact_ids(c, first, second, triangle, ids)
        if first_id != current:
            low = high if first_id > current else np.searchsorted(memory_first, first_id)
            while low < k and memory_first[low] < first_id:
                low += 1
            high = low
            while high < k and memory_first[high] == first_id:
                high += 1
            current = first_id
        for r in range(low, high):
            if memory_second[r] == second_id:
                normal[c] = memory_normal[r]
                for d in range(3):
                    tangential[c, d] = memory_tangential[r, d]
                break
    return normal, tangential


@njit(cache=True)
def remembered(first, second, triangle, ids, keep, lam_n, lam_t):
    """The arrays of a ``record.ContactMemory`` (first id, second id, normal and tangential impulse)
    of a record's contacts where ``keep``, sorted by (first id, second id) as a stable sort would,
    and the largest id among them (the memory's keys need ids below ``record.ID_LIMIT``), and
    whether they are sorted. A record's contacts come nearly in that order (by first particle, a
    row's walls after its pairs): an insertion sort within each first id, unless the first ids are
    out of order (rows not sorted by id: then they are returned as they come, unsorted)."""
    k = 0
    for c in range(len(first)):
        k += keep[c]
    first_id, second_id = np.empty(k, np.int64), np.empty(k, np.int64)
    source = np.empty(k, np.int64)
    largest, in_order, at = np.int64(-1), True, 0
    for c in range(len(first)):
        if keep[c]:
            first_id[at], second_id[at] = contact_ids(c, first, second, triangle, ids)
            source[at] = c
            largest = max(largest, first_id[at], second_id[at])
            in_order = in_order and (at == 0 or first_id[at - 1] <= first_id[at])
            at += 1
    if in_order:
        for at in range(1, k):
            f, s, c = first_id[at], second_id[at], source[at]
            back = at - 1
            while back >= 0 and first_id[back] == f and second_id[back] > s:
                first_id[back + 1], second_id[back + 1], source[back + 1] = first_id[back], second_id[back], source[back]
                back -= 1
            first_id[back + 1], second_id[back + 1], source[back + 1] = f, s, c
    normal, tangential = np.empty(k), np.empty((k, 3))
    for at in range(k):
        normal[at] = lam_n[source[at]]
        for d in range(3):
            tangential[at, d] = lam_t[source[at], d]
    return first_id, second_id, normal, tangential, largest, in_order


@njit(cache=True)
def overlap_rows(first, second, radius, gap, front, tolerance, thorough):
    """The overlaps to remove at a step's end (``solver.remove_overlaps``): of the contacts whose
    ``front`` side faces the other body, those deeper than ``tolerance`` (r_i + r_j). Returns
    their number; the contacts moving them apart could close (in front, deeper than minus the
    deepest overlap; unless ``thorough``, only those of the bodies in an overlap, the world
    aside); the floor of each contact's gap (0 for an overlap, else its gap if negative); the
    least r_i + r_j among the rows."""
    m, n = len(first), len(radius) - 1
    overlapping = np.zeros(m, np.bool_)
    count, deepest = 0, np.inf
    for c in range(m):
        if front[c] and gap[c] < -tolerance * (radius[first[c]] + radius[second[c]]):
            overlapping[c] = True
            count += 1
            deepest = min(deepest, gap[c])
    floor = np.empty(m)
    for c in range(m):
        floor[c] = 0.0 if overlapping[c] else (gap[c] if gap[c] < 0.0 else 0.0)
    if count == 0:
        return 0, np.zeros(0, np.int64), floor, np.inf
    involved = np.zeros(n + 1, np.bool_)
    for c in range(m):
        if overlapping[c]:
            involved[first[c]] = involved[second[c]] = True
    involved[n] = False   # the world (walls)
    rows, k, smallest = np.empty(m, np.int64), 0, np.inf
    for c in range(m):
        if front[c] and gap[c] < -deepest and (thorough or involved[first[c]] or involved[second[c]]):
            rows[k] = c
            k += 1
            smallest = min(smallest, radius[first[c]] + radius[second[c]])
    return count, rows[:k], floor, smallest


@njit(cache=True)
def travels(v, moving, dt, reach):
    """``search.travel_of`` of each body's speed |v| (0 where not ``moving``; None: all move)."""
    out = np.empty(len(v))
    half = 0.5 * reach
    for i in range(len(v)):
        speed = 0.0
        if moving is None or moving[i]:
            speed = np.sqrt(v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2])
        travel = speed * dt * (1 + 1e-9)
        out[i] = travel if travel <= half else half
    return out
