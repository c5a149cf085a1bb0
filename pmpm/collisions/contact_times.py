"""Contact times inside a step (paper eq. 5-7) and the geometry they need, compiled (numba).

Velocities are constant inside a step, so a contact is found from kinematics alone. Two spheres
at separation r_n = x_i − x_j with relative velocity w_n = v_i − v_j touch when
|r_n + w_n τ| = r_i + r_j (eq. 5-7): the smaller root of
|w|² τ² + 2 (r_n·w_n) τ + |r_n|² − (r_i + r_j)² = 0. A sphere touches a wall triangle when the
distance from its centre to the closest point of the triangle (face, edge or vertex) reaches r:
the earliest of the face's plane (foot inside the triangle), the three edges' lines (foot on the
segment) and the three vertices, in the frame of the wall (a rigid wall's velocity at the contact
is subtracted; a rotating wall's path is linearised and the contact checked when it comes).

3-vectors are tuples of floats here (no allocation in the loops). Everything is ``@njit``:
this module is imported only through ``jit.kernels()``.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .settings import APPROACH_TOL, TOUCH_TOL

INF = np.inf


@njit(cache=True)
def vec(array, row):
    """Row ``row`` of an (n, 3) array as a tuple."""
    return (array[row, 0], array[row, 1], array[row, 2])


@njit(cache=True)
def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit(cache=True)
def sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit(cache=True)
def scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


@njit(cache=True)
def cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@njit(cache=True)
def norm(a):
    return np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


@njit(cache=True)
def closest_on_triangle(p, a, b, c):
    """Closest point of triangle (a, b, c) to p and whether it lies inside the face (not on an
    edge or a vertex): the Voronoi regions of the vertices, edges and face in turn."""
    ab, ac, ap = sub(b, a), sub(c, a), sub(p, a)
    d1, d2 = dot(ab, ap), dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return a, False
    bp = sub(p, b)
    d3, d4 = dot(ab, bp), dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return b, False
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return add(a, scale(ab, d1 / (d1 - d3))), False
    cp = sub(p, c)
    d5, d6 = dot(ab, cp), dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return c, False
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return add(a, scale(ac, d2 / (d2 - d6))), False
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        return add(b, scale(sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6)))), False
    total = va + vb + vc
    return add(a, add(scale(ab, vb / total), scale(ac, vc / total))), True


@njit(cache=True)
def rotated(vector, unit, cos, sin):
    """Rodrigues: ``vector`` rotated about the unit axis by the angle of (cos, sin)."""
    return add(add(scale(vector, cos), scale(cross(unit, vector), sin)), scale(unit, dot(unit, vector) * (1.0 - cos)))


@njit(cache=True)
def triangle_at(k, t, A, B, C, N, centre, velocity, omega, moves):
    """Vertices, normal and rotation centre of triangle k at time t into the step: a moving rigid
    triangle turned by Ω t about its centre and shifted by V t (the same motion as ``Walls.moved``)."""
    a, b, c, n, ctr = vec(A, k), vec(B, k), vec(C, k), vec(N, k), vec(centre, k)
    if not moves[k] or t == 0.0:
        return a, b, c, n, ctr
    theta = scale(vec(omega, k), t)
    angle = norm(theta)
    shift = scale(vec(velocity, k), t)
    if angle > 0.0:
        unit = scale(theta, 1.0 / angle)
        cos, sin = np.cos(angle), np.sin(angle)
        a = rotated(sub(a, ctr), unit, cos, sin)
        b = rotated(sub(b, ctr), unit, cos, sin)
        c = rotated(sub(c, ctr), unit, cos, sin)
        n = rotated(n, unit, cos, sin)
        a, b, c = add(a, ctr), add(b, ctr), add(c, ctr)
    return add(a, shift), add(b, shift), add(c, shift), n, add(ctr, shift)


@njit(cache=True)
def surface_velocity(k, point, ctr, n, velocity, omega, rigid):
    """Wall velocity V + Ω × (p − centre) of triangle k at ``point``; a surface-moving wall keeps
    its place, so its normal component is dropped."""
    u = add(vec(velocity, k), cross(vec(omega, k), sub(point, ctr)))
    if not rigid[k]:
        u = sub(u, scale(n, dot(u, n)))
    return u


@njit(cache=True)
def first_root(d, w, radius):
    """First τ >= 0 with |d + w τ| = radius for a point outside the sphere (|d| > radius) moving
    towards it; inf where none (eq. 6-7 with the root taken without cancellation)."""
    A = dot(w, w)
    B = dot(d, w)
    C = dot(d, d) - radius * radius
    disc = B * B - A * C
    if C > 0.0 and B < 0.0 and disc >= 0.0:
        return C / (-B + np.sqrt(disc))
    return INF


@njit(cache=True)
def pair_time(dx, dv, contact, horizon, quiet):
    """Eq. 5-7: the first τ in [0, horizon] with |dx + dv τ| = contact; 0 for touching pairs
    approaching faster than ``quiet`` (m/s, and than round-off); inf where none.
    dx = x_i − x_j, dv = v_i − v_j, contact = r_i + r_j."""
    dist = norm(dx)
    if dist <= contact * (1.0 + TOUCH_TOL):
        closing = -dot(dx, dv) / max(dist, 1e-300)
        return 0.0 if closing > max(quiet, APPROACH_TOL * norm(dv)) else INF
    tau = first_root(dx, dv, contact)
    return tau if tau <= horizon else INF


@njit(cache=True)
def inside_triangle(x, a, b, c, n):
    """The in-plane point x lies in triangle (a, b, c) (edges included, to round-off)."""
    tol = -1e-12 * dot(cross(sub(b, a), sub(c, a)), n)
    return (dot(cross(sub(b, a), sub(x, a)), n) >= tol and dot(cross(sub(c, b), sub(x, b)), n) >= tol
            and dot(cross(sub(a, c), sub(x, c)), n) >= tol)


@njit(cache=True)
def wall_time(p, w, radius, a, b, c, n, horizon, quiet):
    """First τ in [0, horizon] at which a sphere (centre p + w τ, w relative to the triangle)
    touches triangle (a, b, c) from its domain side (normal n); 0 if it touches now and
    approaches faster than ``quiet``; inf where none."""
    q, face = closest_on_triangle(p, a, b, c)
    height = dot(sub(p, a), n)
    sep = sub(p, q)
    dist = norm(sep)
    direction = n if face else scale(sep, 1.0 / max(dist, 1e-300))
    gap = (height if face else dist) - radius
    behind = height < -radius or (not face and height < 0.0)
    if behind:
        return INF
    if gap <= TOUCH_TOL * radius:
        closing = -dot(w, direction)
        return 0.0 if closing > max(quiet, APPROACH_TOL * norm(w)) else INF
    # the distance to a triangle is at least the height over its plane
    wn = dot(w, n)
    if height - radius > max(-wn, 0.0) * horizon:
        return INF
    tau = INF
    if wn < 0.0 and height > radius:  # the face
        t_face = (height - radius) / -wn
        foot = sub(add(p, scale(w, t_face)), scale(n, radius))
        if inside_triangle(foot, a, b, c, n):
            tau = t_face
    for e in range(3):  # the edges (start, end) and their start vertices
        start = a if e == 0 else (b if e == 1 else c)
        end = b if e == 0 else (c if e == 1 else a)
        edge = sub(end, start)
        length = norm(edge)
        unit = scale(edge, 1.0 / length)
        d = sub(p, start)
        d_perp = sub(d, scale(unit, dot(d, unit)))
        w_perp = sub(w, scale(unit, dot(w, unit)))
        t = first_root(d_perp, w_perp, radius)
        if t < tau:
            along = dot(add(d, scale(w, t)), unit)
            if 0.0 <= along <= length:
                tau = t
        tau = min(tau, first_root(d, w, radius))
    if tau < INF and dot(sub(add(p, scale(w, tau)), a), n) < -1e-12 * radius:
        return INF  # reached from behind the plane
    return tau if tau <= horizon else INF


@njit(cache=True)
def wall_contact(p, radius, a, b, c, n):
    """Where a sphere meets a triangle now: (gap, unit normal towards the sphere, face flag, closest
    point, height over the plane). gap < 0: overlapping."""
    q, face = closest_on_triangle(p, a, b, c)
    sep = sub(p, q)
    dist = norm(sep)
    height = dot(sub(p, a), n)
    if face:
        return height - radius, n, True, q, height
    return dist - radius, scale(sep, 1.0 / max(dist, 1e-300)), False, q, height
