"""A step's contacts in time order, compiled (numba): the resting solve at the step's start, then
impacts one by one (paper eq. 3-8), each particle holding its position at its own last event.

The loop works on the step's contact arrays (``ContactRecord``): every contact that may act within
the step was found by the broad search, so an event only recomputes the next contact times of the
contacts of the particles it changed (their adjacency lists). A counter per particle (``stamp``)
invalidates queued events once its velocity changes. Events are popped from a binary heap in time
order (``event_queue``; ties first in, first out).

- An impact approaching faster than ``rest_speed`` gets the closed-form impulse (``impulses.impact``).
- A slower one settles the resting contacts connected to it at that instant (``settle``): every
  contact touching, or closing a face or pair gap within the step, and approaching slower than
  ``rest_speed``, solved together and inelastically by sweeps, instead of a cascade of ever
  smaller bounces.
- Past the event budget, every touching contact is solved inelastically at that instant and
  everything flies to the end of the step (``capped``).
- Touching a deposition wall or a deposited particle deposits a particle (infinite mass, at rest).

``bodies`` = (x, v, w, inv_m, inv_i, radius, free, deposited, clock, stamp), rows 0..n−1 the
particles and row n the world (walls: zero velocity and inverse mass); ``contacts`` = (first,
second, triangle, friction, rolling_friction, restitution, driven, adjacency_start, adjacency);
``walls`` as in ``narrow``.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .contact_times import (dot, norm, pair_time, scale, sub, surface_velocity, triangle_at, vec, wall_contact,
                            wall_time)
from .deposition import deposit, deposit_touching
from .event_queue import heap_pop, heap_push
from .impulses import (apply_impulse, impact, kinetic_energy, limit_energy, relative_velocity, roll_resistance, sweep,
                       warm_start)
from .settings import APPROACH_TOL, CONTACT_TOL, ENERGY_TOL, GAP_TOL, QUIET
from .stats import CAPPED, CLAMPS, EVENTS, PAIR, RESTING, SETTLES, SWEEPS, WALL

RESTING_MODE, CAPPED_MODE = 0, 1
NONE, IMPACT, DEPOSIT, SLOW, RESCHEDULE = range(5)


@njit(cache=True)
def position(x, v, clock, p, t):
    """Where body p is at time t (it moves at v since its clock)."""
    s = t - clock[p]
    return (x[p, 0] + v[p, 0] * s, x[p, 1] + v[p, 1] * s, x[p, 2] + v[p, 2] * s)


@njit(cache=True)
def advance(bodies, p, t):
    x, v, clock = bodies[0], bodies[1], bodies[8]
    x[p, 0], x[p, 1], x[p, 2] = position(x, v, clock, p, t)
    clock[p] = t


@njit(cache=True)
def next_time(c, t, end, quiet, bodies, contacts, walls):
    """Absolute time of contact c's next impact after t (inf: none before ``end``)."""
    x, v, w, inv_m, inv_i, radius, free, deposited, clock, stamp = bodies
    first, second, triangle = contacts[0], contacts[1], contacts[2]
    A, B, C, N, centre, velocity, omega, rigid, moves, deposition = walls
    a, b, k = first[c], second[c], triangle[c]
    horizon = end - t
    if horizon <= 0.0 or not (free[a] or free[b]):
        return np.inf
    pa = position(x, v, clock, a, t)
    if k < 0:
        tau = pair_time(sub(pa, position(x, v, clock, b, t)), sub(vec(v, a), vec(v, b)), radius[a] + radius[b],
                        horizon, quiet)
    else:
        ta, tb, tc, tn, ctr = triangle_at(k, t, A, B, C, N, centre, velocity, omega, moves)
        rel = vec(v, a)
        if moves[k]:  # in the frame of the wall at its closest point (linearised for a rotation)
            q = wall_contact(pa, radius[a], ta, tb, tc, tn)[3]
            rel = sub(rel, surface_velocity(k, q, ctr, tn, velocity, omega, rigid))
        tau = wall_time(pa, rel, radius[a], ta, tb, tc, tn, horizon, quiet)
    return t + tau


@njit(cache=True)
def geometry(c, t, bodies, contacts, walls):
    """Contact c at time t: (gap, normal towards first, face or pair, wall velocity, arm of second,
    in front of the wall)."""
    x, v, w, inv_m, inv_i, radius, free, deposited, clock, stamp = bodies
    first, second, triangle = contacts[0], contacts[1], contacts[2]
    A, B, C, N, centre, velocity, omega, rigid, moves, deposition = walls
    a, b, k = first[c], second[c], triangle[c]
    pa = position(x, v, clock, a, t)
    if k < 0:
        dx = sub(pa, position(x, v, clock, b, t))
        dist = norm(dx)
        return dist - radius[a] - radius[b], scale(dx, 1.0 / max(dist, 1e-300)), True, (0.0, 0.0, 0.0), radius[b], \
            dist > 0.0
    ta, tb, tc, tn, ctr = triangle_at(k, t, A, B, C, N, centre, velocity, omega, moves)
    g, n, face, q, height = wall_contact(pa, radius[a], ta, tb, tc, tn)
    u = surface_velocity(k, q, ctr, tn, velocity, omega, rigid)
    return g, n, face, u, 0.0, height >= (-radius[a] if face else 0.0)


@njit(cache=True)
def qualifies(c, t, mode, rest_speed, horizon, bodies, contacts, walls, work):
    """Whether contact c joins a resting solve at time t; if so its geometry goes into ``work``."""
    x, v, w, inv_m, inv_i, radius, free, deposited, clock, stamp = bodies
    first, second = contacts[0], contacts[1]
    normal, gap, face, u_wall, r_first, r_second = work[0], work[1], work[2], work[3], work[4], work[5]
    a, b = first[c], second[c]
    if not (free[a] or free[b]):
        return False
    g, n, on_face, u, rb, front = geometry(c, t, bodies, contacts, walls)
    if not front:
        return False
    touching = g <= CONTACT_TOL * radius[a]
    if mode == CAPPED_MODE:
        if not touching:
            return False
    else:
        # a gap that shuts within the step slowly: faces and pairs only (the distance to an edge
        # or a vertex is not linear in time: left to the events)
        if not touching and (g > rest_speed * horizon or not on_face):
            return False
        closing = -dot(relative_velocity(a, b, n, radius[a], rb, u, v, w), n)
        if closing >= rest_speed:
            return False
    normal[c, 0], normal[c, 1], normal[c, 2] = n
    gap[c], face[c], r_first[c], r_second[c] = g, on_face, radius[a], rb
    u_wall[c, 0], u_wall[c, 1], u_wall[c, 2] = u
    return True


@njit(cache=True)
def make_work(n, m):
    """Working arrays of a step: per contact normal, gap, face, u_wall, r_first, r_second, target,
    friction, λ_n, λ_t, marks; per body marks, a queue, velocities before a solve, changed bodies."""
    return (np.zeros((m, 3)), np.zeros(m), np.zeros(m, np.bool_), np.zeros((m, 3)), np.zeros(m), np.zeros(m),
            np.zeros(m), np.zeros(m), np.zeros(m), np.zeros((m, 3)), np.zeros(m, np.int64),
            np.zeros(n + 1, np.int64), np.zeros(n + 1, np.int64), np.zeros(m, np.int64), np.zeros((n + 1, 3)),
            np.zeros((n + 1, 3)), np.zeros(n + 1, np.int64), np.zeros(1, np.int64))



@njit(cache=True)
def settle(t, seeds, mode, warm, params, bodies, contacts, walls, work, memory, stats):
    """Solve the resting contacts at time t (all of them without ``seeds``; else those connected to
    the seeds through resting contacts) inelastically: target normal velocity −gap/(time left)
    for a gap (it may close, not more), 0 touching; Coulomb friction where touching; never
    pulling. At t = 0 with ``warm``, the remembered impulses are the start. Then rolling friction
    at the wall contacts that stick. Returns (contacts solved, bodies changed), the changed
    bodies listed in work[16]."""
    x, v, w, inv_m, inv_i, radius, free, deposited, clock, stamp = bodies
    first, second, triangle, mu, mu_r, e, driven, adj_start, adj = contacts
    (normal, gap, face, u_wall, r_first, r_second, target, mu_eff, lam_n, lam_t,
     considered, visit, queue, rows, v0, w0, changed, epoch) = work
    warm_n, warm_t, acc_n, acc_t = memory
    dt, rest_speed, sweeps, tol = params
    n, m = len(radius) - 1, len(first)
    horizon = dt - t
    epoch[0] += 1
    count = 0
    if len(seeds) == 0:
        for c in range(m):
            if qualifies(c, t, mode, rest_speed, horizon, bodies, contacts, walls, work):
                rows[count] = c
                count += 1
    else:  # breadth first over resting contacts from the seeds
        tail = 0
        for s in seeds:
            visit[s] = epoch[0]
            queue[tail] = s
            tail += 1
        head = 0
        while head < tail:
            p = queue[head]
            head += 1
            for at in range(adj_start[p], adj_start[p + 1]):
                c = adj[at]
                if considered[c] == epoch[0]:
                    continue
                considered[c] = epoch[0]
                if not qualifies(c, t, mode, rest_speed, horizon, bodies, contacts, walls, work):
                    continue
                rows[count] = c
                count += 1
                other = second[c] if first[c] == p else first[c]
                if other < n and free[other] and visit[other] != epoch[0]:
                    visit[other] = epoch[0]
                    queue[tail] = other
                    tail += 1
        rows[:count] = np.sort(rows[:count])  # the sweep order of the record, not of the search
    if count == 0:
        return 0, 0
    chosen = rows[:count]
    # the bodies of the solve (once each), moved to t; deposition of the touching ones
    epoch[0] += 1
    nb = 0
    guarded = True
    for c in chosen:
        guarded &= not driven[c]
        for p in (first[c], second[c]):
            if p < n and visit[p] != epoch[0]:
                visit[p] = epoch[0]
                queue[nb] = p
                nb += 1
                advance(bodies, p, t)
    members = queue[:nb].copy()
    n_changed = deposit_touching(chosen, gap, r_first, bodies, contacts, walls[9], changed, stats)
    for p in members:
        for d in range(3):
            v0[p, d], w0[p, d] = v[p, d], w[p, d]
    energy = kinetic_energy(members, inv_m, inv_i, v, w)
    for c in chosen:
        touching = gap[c] <= CONTACT_TOL * r_first[c]
        target[c] = -max(gap[c], 0.0) / horizon
        mu_eff[c] = mu[c] if touching else 0.0
        lam_n[c] = warm_n[c] if warm else 0.0
        for d in range(3):
            lam_t[c, d] = warm_t[c, d] if warm else 0.0
    if warm:
        warm_start(chosen, first, second, normal, r_first, r_second, mu_eff, inv_m, inv_i, v, w, lam_n, lam_t)
    done = sweep(chosen, first, second, normal, r_first, r_second, u_wall, target, mu_eff, inv_m, inv_i, v, w,
                 lam_n, lam_t, sweeps, tol)
    gained = guarded and kinetic_energy(members, inv_m, inv_i, v, w) > energy * (1.0 + ENERGY_TOL) + 1e-300
    if warm and (gained or done == sweeps):
        # the remembered impulses were the wrong start (they can wedge frictional loops, where the
        # sweeps then pump internal impulses instead of converging): again from nothing
        for p in members:
            for d in range(3):
                v[p, d], w[p, d] = v0[p, d], w0[p, d]
        for c in chosen:
            lam_n[c] = 0.0
            lam_t[c, 0] = lam_t[c, 1] = lam_t[c, 2] = 0.0
        done += sweep(chosen, first, second, normal, r_first, r_second, u_wall, target, mu_eff, inv_m, inv_i, v, w,
                      lam_n, lam_t, sweeps, tol)
        gained = guarded and kinetic_energy(members, inv_m, inv_i, v, w) > energy * (1.0 + ENERGY_TOL) + 1e-300
    if gained:
        stats[CLAMPS] += 1
        limit_energy(members, inv_m, inv_i, v, w, v0, w0, energy, ENERGY_TOL)
    rolling = np.zeros(count, np.int64)
    n_rolling = 0
    for c in chosen:
        size = np.sqrt(lam_t[c, 0] ** 2 + lam_t[c, 1] ** 2 + lam_t[c, 2] ** 2)
        if (triangle[c] >= 0 and mu_r[c] > 0 and lam_n[c] > 0 and size < mu_eff[c] * lam_n[c] * (1 - 1e-9)):
            rolling[n_rolling] = c
            n_rolling += 1
    roll_resistance(rolling[:n_rolling], first, triangle, normal, u_wall, walls[6], lam_n, mu_r, inv_m, inv_i, radius,
                    v, w)
    for c in chosen:
        acc_n[c] += lam_n[c]
        for d in range(3):
            acc_t[c, d] += lam_t[c, d]
    # the bodies whose velocities the solve changed beyond its own round-off
    threshold = 1e-6 * QUIET * rest_speed
    for p in members:
        if not free[p] or deposited[p]:
            continue
        change = 0.0
        for d in range(3):
            change = max(change, abs(v[p, d] - v0[p, d]) + radius[p] * abs(w[p, d] - w0[p, d]))
        if change > threshold:
            changed[n_changed] = p
            n_changed += 1
    stats[RESTING] += count
    stats[SWEEPS] += done
    stats[SETTLES] += 1
    return count, n_changed


@njit(cache=True)
def resolve(t, c, rest_speed, bodies, contacts, walls, stats):
    """The event of contact c at time t: its bodies moved to t, then an impulse, a deposition, a
    slow contact for ``settle`` or a miss to reschedule. Returns (kind, particle to deposit)."""
    x, v, w, inv_m, inv_i, radius, free, deposited, clock, stamp = bodies
    first, second, triangle, mu, e = contacts[0], contacts[1], contacts[2], contacts[3], contacts[5]
    a, b, k = first[c], second[c], triangle[c]
    advance(bodies, a, t)
    if k < 0:
        advance(bodies, b, t)
    g, n, face, u_wall, rb, front = geometry(c, t, bodies, contacts, walls)
    if k >= 0 and g > GAP_TOL * radius[a]:
        return RESCHEDULE, a  # a rotating wall's linearised path missed: look again from here
    u = relative_velocity(a, b, n, radius[a], rb, u_wall, v, w)
    closing = -dot(u, n)
    if closing <= APPROACH_TOL * norm(u):
        return NONE, -1
    if k < 0:
        stats[PAIR] += 1
        if deposited[b] and free[a]:
            return DEPOSIT, a
        if deposited[a] and free[b]:
            return DEPOSIT, b
    else:
        stats[WALL] += 1
        if walls[9][k]:
            return DEPOSIT, a
    if closing < rest_speed:
        return SLOW, -1
    k_n = inv_m[a] + inv_m[b]
    k_t = k_n + inv_i[a] * radius[a] ** 2 + inv_i[b] * rb * rb
    J, sticking = impact(u, n, k_n, k_t, e[c], mu[c])
    apply_impulse(a, b, J, n, radius[a], rb, inv_m, inv_i, v, w)
    return IMPACT, -1


@njit(cache=True)
def run_events(bodies, contacts, walls, memory, dt, rest_speed, max_events, speed_bound, sweeps, settle_sweeps, tol,
               stats):
    """The step (see the module's docstring); every body ends at time ``dt``. Returns the largest
    speed a free particle reached; if it is above ``speed_bound`` (the speed the broad search
    assumed), the loop stopped there and the step is unfinished (the caller searches again).
    ``memory`` = (remembered λ_n, λ_t, accumulated λ_n, λ_t) per contact."""
    x, v, w, inv_m, inv_i, radius, free, deposited, clock, stamp = bodies
    first, second, triangle, mu, mu_r, e, driven, adj_start, adj = contacts
    n, m = len(radius) - 1, len(first)
    work = make_work(n, m)
    scheduled = np.zeros(m, np.int64)
    batch = 0
    params = (dt, rest_speed, sweeps, tol)
    inside = (dt, rest_speed, settle_sweeps, tol)  # the settles after slow impacts
    end = dt * (1 - 1e-9)  # contacts at the very end of the step are the next step's
    quiet = QUIET * rest_speed
    no_seeds = np.zeros(0, np.int64)
    seeds = np.zeros(2, np.int64)
    if rest_speed > 0 and m > 0:
        settle(0.0, no_seeds, RESTING_MODE, True, params, bodies, contacts, walls, work, memory, stats)
    top = 0.0
    for p in range(n):
        if free[p]:
            top = max(top, norm(vec(v, p)))
    if top > speed_bound:
        return top
    heap = np.empty((2 * m + 16, 5))
    size, seq = 0, 0
    for c in range(m):
        t = next_time(c, 0.0, end, quiet, bodies, contacts, walls)
        if t < np.inf:
            heap, size = heap_push(heap, size, t, seq, c, stamp[first[c]], stamp[second[c]])
            seq += 1
    changed = work[16]
    while size > 0:
        t, c, sa, sb, size = heap_pop(heap, size)
        if sa != stamp[first[c]] or sb != stamp[second[c]]:
            continue  # a body changed since this was queued
        if stats[EVENTS] >= max_events:
            stats[CAPPED] = 1
            for p in range(n):
                advance(bodies, p, t)
            settle(t, no_seeds, CAPPED_MODE, False, params, bodies, contacts, walls, work, memory, stats)
            break
        stats[EVENTS] += 1
        kind, p = resolve(t, c, rest_speed, bodies, contacts, walls, stats)
        n_changed = 0
        if kind == IMPACT:
            for q in (first[c], second[c]):
                if q < n and free[q]:
                    changed[n_changed] = q
                    n_changed += 1
        elif kind == DEPOSIT:
            deposit(p, bodies[1], bodies[2], bodies[3], bodies[4], bodies[6], bodies[7], stats)
            changed[0] = p
            n_changed = 1
        elif kind == RESCHEDULE:
            changed[0] = p
            n_changed = 1
        elif kind == SLOW:
            count = 0
            for q in (first[c], second[c]):
                if q < n and free[q]:
                    seeds[count] = q
                    count += 1
            n_changed = settle(t, seeds[:count], RESTING_MODE, False, inside, bodies, contacts, walls, work, memory,
                               stats)[1]
        # the changed bodies: new stamps first, then each of their contacts queued once
        batch += 1
        for r in range(n_changed):
            stamp[changed[r]] += 1
        for r in range(n_changed):
            q = changed[r]
            speed = norm(vec(v, q))
            top = max(top, speed)
            if free[q] and speed > speed_bound:
                return top
            for at in range(adj_start[q], adj_start[q + 1]):
                d = adj[at]
                if scheduled[d] == batch:
                    continue
                scheduled[d] = batch
                t_next = next_time(d, t, end, quiet, bodies, contacts, walls)
                if t_next < np.inf:
                    heap, size = heap_push(heap, size, t_next, seq, d, stamp[first[d]], stamp[second[d]])
                    seq += 1
    for p in range(n):
        advance(bodies, p, dt)
    return top
