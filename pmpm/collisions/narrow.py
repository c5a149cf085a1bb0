"""The narrow phase, compiled (numba): from candidate pairs and (particle, triangle) candidates to
contacts with a gap, a normal and the first contact time at the step's velocities (eq. 5-7).

``walls`` here is the tuple of the ``Walls`` arrays the kernels use, in this order:
a, b, c, normal, center, velocity, angular_velocity, rigid, moves, deposition
(see ``search.wall_arrays``).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .contact_times import (dot, norm, pair_time, scale, sub, surface_velocity, triangle_at, vec, wall_contact,
                            wall_time)
from .settings import CONTACT_TOL, PARALLEL


@njit(cache=True)
def can_close(gap, speed, horizon, radius):
    """A contact acts within ``horizon`` (s): touching (gap <= 1e-6 r), or its gap (m) closes at
    the relative speed (m/s) of the centres (of a centre and the wall surface)."""
    return gap <= speed * horizon + CONTACT_TOL * radius


@njit(cache=True)
def pair_contacts(first, second, x, v, radius, free, reach, dt):
    """Candidate pairs (first, second) kept where one is free and the gap is at most ``reach`` (m)
    beyond touching. Returns keep (k,) bool; acts (k,) bool: touching, or the gap can close
    within ``dt`` at the relative speed of the centres; normal (k, 3) towards first; gap (k,) m;
    the first contact time (k,) s within ``dt`` at the current velocities (inf: none)."""
    count = len(first)
    keep = np.zeros(count, np.bool_)
    acts = np.zeros(count, np.bool_)
    normal = np.zeros((count, 3))
    gap = np.zeros(count)
    time = np.full(count, np.inf)
    for c in range(count):
        a, b = first[c], second[c]
        if not (free[a] or free[b]):
            continue
        dx = sub(vec(x, a), vec(x, b))
        dist = norm(dx)
        contact = radius[a] + radius[b]
        if dist <= 0.0 or dist - contact > reach + CONTACT_TOL * contact:
            continue
        dv = sub(vec(v, a), vec(v, b))
        keep[c] = True
        acts[c] = can_close(dist - contact, norm(dv), dt, radius[a])
        normal[c, 0], normal[c, 1], normal[c, 2] = scale(dx, 1.0 / dist)
        gap[c] = dist - contact
        time[c] = pair_time(dx, dv, contact, dt, 0.0)
    return keep, acts, normal, gap, time


@njit(cache=True)
def wall_contacts(particle, triangle, x, v, radius, walls, travel, reach, dt):
    """Candidate (particle, triangle) pairs kept where the sphere is on the domain side and its gap
    is at most ``reach`` + the triangle's ``travel`` (m). Returns keep; acts (touching, or closing
    within ``dt`` at the speed of the centre relative to the wall surface); normal (towards the
    sphere); gap; face (bool: the closest point is inside the face); the wall surface velocity
    at the contact point (k, 3); the first contact time within ``dt`` (inf: none)."""
    A, B, C, N, centre, velocity, omega, rigid, moves, deposition = walls
    count = len(particle)
    keep = np.zeros(count, np.bool_)
    acts = np.zeros(count, np.bool_)
    normal = np.zeros((count, 3))
    gap = np.zeros(count)
    face = np.zeros(count, np.bool_)
    u_wall = np.zeros((count, 3))
    time = np.full(count, np.inf)
    for c in range(count):
        p, k = particle[c], triangle[c]
        a, b, cc, n, ctr = triangle_at(k, 0.0, A, B, C, N, centre, velocity, omega, moves)
        xp = vec(x, p)
        g, direction, on_face, q, height = wall_contact(xp, radius[p], a, b, cc, n)
        behind = height < (-radius[p] if on_face else 0.0) - travel[k]
        if behind or g > reach + travel[k] + CONTACT_TOL * radius[p]:
            continue
        keep[c] = True
        normal[c, 0], normal[c, 1], normal[c, 2] = direction
        gap[c] = g
        face[c] = on_face
        u = surface_velocity(k, q, ctr, n, velocity, omega, rigid)
        u_wall[c, 0], u_wall[c, 1], u_wall[c, 2] = u
        acts[c] = can_close(g, norm(sub(vec(v, p), u)), dt, radius[p])
        w = sub(vec(v, p), u) if moves[k] else vec(v, p)
        time[c] = wall_time(xp, w, radius[p], a, b, cc, n, dt, 0.0)
    return keep, acts, normal, gap, face, u_wall, time


@njit(cache=True)
def closing_pairs(pairs, x, v, radius, free, reach, horizon, tol):
    """(k,) bool over candidate ``pairs`` (k, 2): at least one free, centres apart, and a gap
    g = |x_i − x_j| − r_i − r_j with g <= ``reach`` + tol (r_i + r_j) and
    g <= |v_i − v_j| ``horizon`` + tol r_i: the pair can close within ``horizon`` (s)."""
    keep = np.zeros(len(pairs), np.bool_)
    for c in range(len(pairs)):
        a, b = pairs[c, 0], pairs[c, 1]
        if not (free[a] or free[b]):
            continue
        dx = sub(vec(x, a), vec(x, b))
        dist = norm(dx)
        g = dist - (radius[a] + radius[b])
        if dist <= 0 or g > tol * (radius[a] + radius[b]) + reach:
            continue
        keep[c] = g <= norm(sub(vec(v, a), vec(v, b))) * horizon + tol * radius[a]  # can_close, any tol
    return keep


@njit(cache=True)
def parallel_duplicates(rows, first, triangle, gap, normal, radius):
    """(len(rows),) bool: wall contacts among ``rows`` (sorted by particle) to drop because a
    higher-ranked wall contact of the same particle has a (nearly) parallel normal: a sphere over
    the shared edge of two coplanar triangles touches both at one point, and nearly parallel
    constraints add nothing but ill-conditioning. The clearly smaller gap (by more than 1e-6 r)
    ranks first, then the lower triangle index: not whether the closest point is on the face or
    the edge, which flips with round-off there and would lose the remembered impulse."""
    drop = np.zeros(len(rows), np.bool_)
    start = 0
    while start < len(rows):
        stop = start
        while stop < len(rows) and first[rows[stop]] == first[rows[start]]:
            stop += 1
        for s in range(start, stop):
            cs = rows[s]
            if triangle[cs] < 0:
                continue
            tol = CONTACT_TOL * radius[first[cs]]
            for o in range(start, stop):
                co = rows[o]
                if o == s or triangle[co] < 0:
                    continue
                if abs(gap[co] - gap[cs]) > tol:
                    ranks_before = gap[co] < gap[cs]
                else:
                    ranks_before = triangle[co] < triangle[cs]
                if ranks_before and dot(vec(normal, co), vec(normal, cs)) > PARALLEL:
                    drop[s] = True
                    break
        start = stop
    return drop


@njit(cache=True)
def end_gaps(first, second, triangle, x, radius, walls):
    """Gap (m) and normal of each contact at the positions ``x`` (walls at their current
    geometry), and whether a wall contact's sphere is on the domain side."""
    A, B, C, N, centre, velocity, omega, rigid, moves, deposition = walls
    count = len(first)
    gap = np.zeros(count)
    normal = np.zeros((count, 3))
    front = np.ones(count, np.bool_)
    for c in range(count):
        a, k = first[c], triangle[c]
        if k < 0:
            dx = sub(vec(x, a), vec(x, second[c]))
            dist = norm(dx)
            gap[c] = dist - radius[a] - radius[second[c]]
            n = scale(dx, 1.0 / max(dist, 1e-300))
        else:
            g, n, on_face, q, height = wall_contact(vec(x, a), radius[a], vec(A, k), vec(B, k), vec(C, k), vec(N, k))
            gap[c] = g
            front[c] = height >= (-radius[a] if on_face else 0.0)
        normal[c, 0], normal[c, 1], normal[c, 2] = n
    return gap, normal, front

