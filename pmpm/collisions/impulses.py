"""Impulses at sphere contacts, compiled (numba): one impact in closed form, sets of contacts by
projected Gauss–Seidel sweeps, rolling friction, and the removal of overlaps by moving positions.

Bodies are spheres: the arms from the centres to the contact point are −r_i n and r_j n, so the
contact-point velocity of i relative to j is u = v_i − v_j − u_wall − (r_i ω_i + r_j ω_j) × n and an
impulse J on i (−J on j) changes v_i by J/m_i, v_j by −J/m_j, ω_i by −r_i (n × J)/I_i and ω_j by
−r_j (n × J)/I_j. A wall, a fixed, prescribed or deposited particle has zero inverse mass.
Normal and tangential responses decouple for spheres (k_n = 1/m_i + 1/m_j along n,
k_t = k_n + r_i²/I_i + r_j²/I_j across it), which the closed forms below use.

Projected Gauss–Seidel takes one contact at a time in the order given: the normal impulse λ_n is
clamped to >= 0 and the tangential impulse λ_t to the Coulomb cone |λ_t| <= μ λ_n, both on the
impulses accumulated so far (so impulses already applied are the warm start), and the change is
applied to both bodies at once, so the next contact sees it. Each contact alone is solved exactly
by one update (the closed form), so a set converges to the simultaneous solution.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from .contact_times import cross, dot, norm, scale, sub, vec


@njit(cache=True)
def impact(u, n, k_n, k_t, e, mu):
    """Impulse on body i at one contact (the paper's impact): normal restitution e, Coulomb
    friction μ. u: contact-point velocity of i relative to j, n: unit normal towards i.

    J_n = −(1 + e) u_n / k_n;  J_t = −u_t / k_t (stops sliding), scaled to μ J_n if larger.
    Returns (J, sticking)."""
    u_n = dot(u, n)
    j_n = -(1.0 + e) * u_n / k_n
    u_t = sub(u, scale(n, u_n))
    stick = scale(u_t, -1.0 / k_t)
    size = norm(stick)
    limit = mu * j_n
    if size <= limit:
        return (j_n * n[0] + stick[0], j_n * n[1] + stick[1], j_n * n[2] + stick[2]), True
    s = limit / size
    return (j_n * n[0] + s * stick[0], j_n * n[1] + s * stick[1], j_n * n[2] + s * stick[2]), False


@njit(cache=True, inline="always")
def apply_impulse(a, b, J, n, r_a, r_b, inv_m, inv_i, v, w):
    """J on body a, −J on body b, at the contact with normal n (towards a)."""
    c = cross(n, J)
    ma, mb = inv_m[a], inv_m[b]
    wa, wb = inv_i[a] * r_a, inv_i[b] * r_b
    for d in range(3):
        v[a, d] += ma * J[d]
        v[b, d] -= mb * J[d]
        w[a, d] -= wa * c[d]
        w[b, d] -= wb * c[d]


@njit(cache=True, inline="always")
def relative_velocity(a, b, n, r_a, r_b, u_wall, v, w):
    """Contact-point velocity of body a relative to body b (and the wall surface u_wall)."""
    s = (r_a * w[a, 0] + r_b * w[b, 0], r_a * w[a, 1] + r_b * w[b, 1], r_a * w[a, 2] + r_b * w[b, 2])
    return sub(sub(sub(vec(v, a), vec(v, b)), u_wall), cross(s, n))


@njit(cache=True, inline="always")
def project(c, inv_kn, inv_kt, first, second, normal, r_first, r_second, u_wall, target, mu, inv_m, inv_i, v, w,
            lam_n, lam_t):
    """One projected update of contact c (the closed form, on the impulses so far)."""
    a, b = first[c], second[c]
    n = vec(normal, c)
    u = relative_velocity(a, b, n, r_first[c], r_second[c], vec(u_wall, c), v, w)
    u_n = dot(u, n)
    old_n = lam_n[c]
    new_n = max(old_n + (target[c] - u_n) * inv_kn, 0.0)
    t0 = lam_t[c, 0] - (u[0] - u_n * n[0]) * inv_kt
    t1 = lam_t[c, 1] - (u[1] - u_n * n[1]) * inv_kt
    t2 = lam_t[c, 2] - (u[2] - u_n * n[2]) * inv_kt
    size = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    limit = mu[c] * new_n
    if size > limit:  # outside the cone: slide, at μ λ_n
        f = limit / size
        t0, t1, t2 = t0 * f, t1 * f, t2 * f
    d_n = new_n - old_n
    J = (d_n * n[0] + t0 - lam_t[c, 0], d_n * n[1] + t1 - lam_t[c, 1], d_n * n[2] + t2 - lam_t[c, 2])
    lam_n[c] = new_n
    lam_t[c, 0], lam_t[c, 1], lam_t[c, 2] = t0, t1, t2
    apply_impulse(a, b, J, n, r_first[c], r_second[c], inv_m, inv_i, v, w)


@njit(cache=True, inline="always")
def inverse_masses(c, first, second, r_first, r_second, inv_m, inv_i):
    """(1/k_n, 1/k_t) of contact c; 0 for two bodies of infinite mass (a particle deposited this
    step on a wall: nothing moves)."""
    a, b = first[c], second[c]
    k_n = inv_m[a] + inv_m[b]
    k_t = k_n + inv_i[a] * r_first[c] ** 2 + inv_i[b] * r_second[c] ** 2
    return (1.0 / k_n if k_n > 0 else 0.0), (1.0 / k_t if k_t > 0 else 0.0)


@njit(cache=True)
def sweep(rows, first, second, normal, r_first, r_second, u_wall, target, mu, inv_m, inv_i, v, w,
          lam_n, lam_t, sweeps, tol):
    """Projected Gauss–Seidel over contacts ``rows`` until a sweep changes no contact-point velocity
    (|Δv| + r |Δω| per component) by more than ``tol`` (m/s), or ``sweeps`` sweeps are done;
    returns the sweeps made.

    Each contact c is driven to the normal relative velocity ``target[c]`` (m/s; it may end
    faster where λ_n = 0). ``lam_n[c]`` (N s) and ``lam_t[c]`` (N s, (3,)) are the impulses on
    ``first[c]`` accumulated so far (already applied to v, w); updated in place, as are v and w.

    Notes
    -----
    Plain sweeps converge slowly where rotation couples the friction of a sphere's contacts (a
    ball wedged between a floor and a wall: 0.998 per sweep). Each sweep is followed by the
    nonsmooth nonlinear conjugate gradient step of Silcowski (2011, as in Tonge's thesis): with
    r_k the change the sweep made to the impulses, β = |r_k|² / |r_{k−1}|² and, if β <= 1,
    impulses += β p, p ← β p − r_k (else p ← 0, a restart). The sweep after it projects again, and
    the last operation before stopping is always a sweep, so the impulses end admissible.
    """
    count = len(rows)
    inv_kn = np.empty(count)
    inv_kt = np.empty(count)
    for r in range(count):
        inv_kn[r], inv_kt[r] = inverse_masses(rows[r], first, second, r_first, r_second, inv_m, inv_i)
    # the bodies that can move, and their velocities before each sweep
    seen = np.zeros(len(inv_m), np.bool_)
    members = np.empty(2 * count, np.int64)
    n_members = 0
    for c in rows:
        for body in (first[c], second[c]):
            if inv_m[body] > 0 and not seen[body]:
                seen[body] = True
                members[n_members] = body
                n_members += 1
    members = members[:n_members]
    arm = np.zeros(len(inv_m))  # a body's largest arm: its spin's share of a contact-point velocity
    for c in rows:
        arm[first[c]] = max(arm[first[c]], r_first[c])
        arm[second[c]] = max(arm[second[c]], r_second[c])
    start_v = np.empty((n_members, 6))
    before = np.empty((count, 4))
    direction = np.zeros((count, 4))
    previous = 0.0
    done = 0
    for s in range(sweeps):
        keep_impulses(rows, lam_n, lam_t, before)
        for k in range(n_members):
            for d in range(3):
                start_v[k, d], start_v[k, 3 + d] = v[members[k], d], w[members[k], d]
        for r in range(count):
            project(rows[r], inv_kn[r], inv_kt[r], first, second, normal, r_first, r_second, u_wall, target, mu, inv_m,
                    inv_i, v, w, lam_n, lam_t)
        done = s + 1
        largest = 0.0  # the largest change of a contact-point velocity over the sweep
        for k in range(n_members):
            change = 0.0
            for d in range(3):
                change = max(change, abs(v[members[k], d] - start_v[k, d])
                             + arm[members[k]] * abs(w[members[k], d] - start_v[k, 3 + d]))
            largest = max(largest, change)
        if largest <= tol:
            break
        size = impulse_change(rows, lam_n, lam_t, before)
        beta = size / previous if previous > 0 else 2.0  # 2: restart
        previous = size
        conjugate_step(rows, beta, before, direction, first, second, normal, r_first, r_second, inv_m, inv_i, v, w,
                       lam_n, lam_t)
    return done


@njit(cache=True)
def keep_impulses(rows, lam_n, lam_t, before):
    """before[r] = (λ_n, λ_t) of contact rows[r]: the impulses before a sweep."""
    for r in range(len(rows)):
        c = rows[r]
        before[r, 0], before[r, 1], before[r, 2], before[r, 3] = lam_n[c], lam_t[c, 0], lam_t[c, 1], lam_t[c, 2]


@njit(cache=True, inline="always")
def squared_change(c, r, lam_n, lam_t, before):
    """The squared change of contact c's impulses since ``before[r]`` (N² s²)."""
    return ((lam_n[c] - before[r, 0]) ** 2 + (lam_t[c, 0] - before[r, 1]) ** 2
            + (lam_t[c, 1] - before[r, 2]) ** 2 + (lam_t[c, 2] - before[r, 3]) ** 2)


@njit(cache=True)
def impulse_change(rows, lam_n, lam_t, before):
    """|r_k|²: the squared change of the impulses of contacts ``rows`` since ``before`` (N² s²)."""
    size = 0.0
    for r in range(len(rows)):
        size += squared_change(rows[r], r, lam_n, lam_t, before)
    return size


@njit(cache=True)
def conjugate_step(rows, beta, before, direction, first, second, normal, r_first, r_second, inv_m, inv_i, v, w,
                   lam_n, lam_t, keep=False):
    """The nonsmooth conjugate gradient step after a sweep (``sweep``'s notes): if β <= 1 the impulses
    of ``rows`` move by β p and v, ω with them, and p ← β p + r_k (the sweep's change since
    ``before``); else p ← 0 (a restart). ``direction`` (len(rows), 4): p, updated in place; with
    ``keep``, ``before`` takes the impulses after the step (those the next sweep starts from)."""
    for r in range(len(rows)):
        c = rows[r]
        change = (lam_n[c] - before[r, 0], lam_t[c, 0] - before[r, 1], lam_t[c, 1] - before[r, 2],
                  lam_t[c, 2] - before[r, 3])
        step = (0.0, 0.0, 0.0, 0.0)
        if beta <= 1.0:
            step = (beta * direction[r, 0], beta * direction[r, 1], beta * direction[r, 2], beta * direction[r, 3])
            lam_n[c] += step[0]
            lam_t[c, 0] += step[1]
            lam_t[c, 1] += step[2]
            lam_t[c, 2] += step[3]
            n = vec(normal, c)
            J = (step[0] * n[0] + step[1], step[0] * n[1] + step[2], step[0] * n[2] + step[3])
            apply_impulse(first[c], second[c], J, n, r_first[c], r_second[c], inv_m, inv_i, v, w)
        for d in range(4):
            direction[r, d] = step[d] + change[d] if beta <= 1.0 else 0.0
        if keep:
            before[r, 0], before[r, 1], before[r, 2], before[r, 3] = lam_n[c], lam_t[c, 0], lam_t[c, 1], lam_t[c, 2]


@njit(cache=True)
def sweep_from(rows, inv_kn, inv_kt, before, first, second, normal, r_first, r_second, u_wall, target, mu, inv_m,
               inv_i, v, w, lam_n, lam_t):
    """One projected Gauss–Seidel sweep over contacts ``rows`` (``sweep`` taken apart: a rank's block of
    contacts between two exchanges of shadow copies, ``subdomains``), whose impulses before it are
    ``before`` (len(rows), 4; ``conjugate_step`` with ``keep`` sets them). ``inv_kn``, ``inv_kt``
    (len(rows),): 1/k_n, 1/k_t per row. Returns |r_k|², the squared change the sweep made to the impulses."""
    size = 0.0
    for r in range(len(rows)):
        c = rows[r]
        project(c, inv_kn[r], inv_kt[r], first, second, normal, r_first, r_second, u_wall, target, mu, inv_m, inv_i,
                v, w, lam_n, lam_t)
        size += squared_change(c, r, lam_n, lam_t, before)
    return size


@njit(cache=True)
def split_at_shared(rows, shared, first, second, r_first, r_second, inv_m, inv_i):
    """``subdomains.block_sweeps``' contacts: ``rows`` split into those touching a body where
    ``shared`` (border) and the others (inner), each in order with its 1/k_n and 1/k_t; returns
    (border rows, 1/k_n, 1/k_t, inner rows, 1/k_n, 1/k_t, changing: (bodies,) bool, the bodies
    the border contacts touch)."""
    count = len(rows)
    border, inner = np.empty(count, np.int64), np.empty(count, np.int64)
    inv_kn, inv_kt = np.empty(count), np.empty(count)
    changing = np.zeros(len(inv_m), np.bool_)
    n_border = 0
    for r in range(count):
        c = rows[r]
        if shared[first[c]] or shared[second[c]]:
            border[n_border] = r
            n_border += 1
            changing[first[c]] = changing[second[c]] = True
        else:
            inner[r - n_border] = r
        inv_kn[r], inv_kt[r] = inverse_masses(c, first, second, r_first, r_second, inv_m, inv_i)
    border, inner = border[:n_border], inner[:count - n_border]
    return rows[border], inv_kn[border], inv_kt[border], rows[inner], inv_kn[inner], inv_kt[inner], changing


@njit(cache=True)
def watched_bodies(rows, first, second, r_first, r_second, inv_m, owned):
    """The bodies of contacts ``rows`` whose contact-point velocities a block sweep's stopping test
    watches (where ``owned``, of finite mass), ascending, and every body's arm: its radius where it
    touches, 0 elsewhere and for the world."""
    arm = np.zeros(len(inv_m))
    for c in rows:
        arm[second[c]] = r_second[c]
        arm[first[c]] = r_first[c]
    watched = np.empty(len(inv_m), np.int64)
    count = 0
    for b in range(len(inv_m)):
        if owned[b] and inv_m[b] > 0 and arm[b] > 0:
            watched[count] = b
            count += 1
    return watched[:count].copy(), arm


@njit(cache=True)
def change_since(bodies, v, w, arm, saved):
    """The largest change of a contact point's velocity component, |Δv_d| + arm |Δω_d|, of
    ``bodies`` since their (v, ω) were ``saved`` (len(bodies), 6), which then takes them (m/s)."""
    largest = 0.0
    for k in range(len(bodies)):
        b = bodies[k]
        for d in range(3):
            largest = max(largest, abs(v[b, d] - saved[k, d]) + arm[b] * abs(w[b, d] - saved[k, 3 + d]))
            saved[k, d], saved[k, 3 + d] = v[b, d], w[b, d]
    return largest


@njit(cache=True)
def warm_start(rows, first, second, normal, r_first, r_second, mu, inv_m, inv_i, v, w, lam_n, lam_t):
    """Apply remembered impulses (in ``lam_n``, ``lam_t``) after projecting them on today's normals
    and Coulomb cones; the projected values replace them."""
    for c in rows:
        ln = max(lam_n[c], 0.0)
        n = vec(normal, c)
        t = sub(vec(lam_t, c), scale(n, dot(vec(lam_t, c), n)))
        size = norm(t)
        if size > mu[c] * ln:
            t = scale(t, mu[c] * ln / size)
        lam_n[c] = ln
        lam_t[c, 0], lam_t[c, 1], lam_t[c, 2] = t
        apply_impulse(first[c], second[c], (ln * n[0] + t[0], ln * n[1] + t[1], ln * n[2] + t[2]), n,
                      r_first[c], r_second[c], inv_m, inv_i, v, w)


@njit(cache=True)
def roll_resistance(rows, first, triangle, normal, u_wall, wall_omega, lam_n, mu_r, inv_m, inv_i, radius, v, w):
    """Rolling friction at resting wall contacts ``rows``: the torque μ_r N r against rolling, with
    the rolling constraint kept, slows the rolling velocity relative to the wall by
    (5/7) μ_r λ_n / m and the spin with it (Δω = n × Δv / r); the same torque against the spin
    about the contact normal relative to the wall's (``wall_omega`` per triangle; a point contact
    has no other resistance to it) slows that spin by μ_r λ_n r / I. Neither past a stop."""
    for c in rows:
        i = first[c]
        n = vec(normal, c)
        relative = dot(vec(w, i), n) - dot(vec(wall_omega, triangle[c]), n)
        twist = min(mu_r[c] * lam_n[c] * radius[i] * inv_i[i], abs(relative))
        for d in range(3):
            w[i, d] -= np.sign(relative) * twist * n[d]
        rolling = sub(vec(v, i), vec(u_wall, c))
        rolling = sub(rolling, scale(n, dot(rolling, n)))
        speed = norm(rolling)
        if speed <= 0.0:
            continue
        slow = min(5.0 / 7.0 * mu_r[c] * lam_n[c] * inv_m[i], speed)
        dv = scale(rolling, -slow / speed)
        spin = cross(n, dv)
        for d in range(3):
            v[i, d] += dv[d]
            w[i, d] += spin[d] / radius[i]


@njit(cache=True)
def kinetic_energy(bodies, inv_m, inv_i, v, w):
    """Σ ½ m |v|² + ½ I |ω|² over ``bodies`` of finite mass (J)."""
    total = 0.0
    for b in bodies:
        if inv_m[b] > 0:
            total += 0.5 * dot(vec(v, b), vec(v, b)) / inv_m[b] + 0.5 * dot(vec(w, b), vec(w, b)) / inv_i[b]
    return total


@njit(cache=True)
def limit_energy(bodies, inv_m, inv_i, v, w, v0, w0, energy_before, tol):
    """If the velocities of ``bodies`` have more kinetic energy than ``energy_before`` (relative
    ``tol``), scale their change since (v0, w0) by the largest s in [0, 1] that keeps the energy:
    E(s) = E0 + s a + s² b is a parabola in s. Returns True if it scaled."""
    after = kinetic_energy(bodies, inv_m, inv_i, v, w)
    if after <= energy_before * (1.0 + tol) + 1e-300:
        return False
    a, b = 0.0, 0.0
    for k in bodies:
        if inv_m[k] > 0:
            for d in range(3):
                dv, dw = v[k, d] - v0[k, d], w[k, d] - w0[k, d]
                a += dv * v0[k, d] / inv_m[k] + dw * w0[k, d] / inv_i[k]
                b += 0.5 * (dv * dv / inv_m[k] + dw * dw / inv_i[k])
    s = 0.0
    if b > 0 and a < 0:
        s = min(1.0, -a / b)
    for k in bodies:
        for d in range(3):
            v[k, d] = v0[k, d] + s * (v[k, d] - v0[k, d])
            w[k, d] = w0[k, d] + s * (w[k, d] - w0[k, d])
    return True


@njit(cache=True)
def separate(rows, first, second, normal, gap, floor, inv_m, x, sweeps, tol):
    """Remove overlaps by moving positions only (velocities untouched, so no kinetic energy is
    made): Gauss–Seidel on displacement impulses p_c >= 0 along the normals, mass-weighted (a
    body of infinite mass stays), until no contact's gap + (δ_i − δ_j)·n is below ``floor[c]``
    (m; 0 for an overlap to remove, the gap itself for one within tolerance) by more than
    ``tol`` (m), or ``sweeps`` sweeps. ``x`` is updated in place; returns the sweeps made."""
    count = len(rows)
    push = np.zeros(count)
    moved = np.zeros((x.shape[0], 3))
    done = 0
    for s in range(sweeps):
        worst = 0.0
        for r in range(count):
            c = rows[r]
            a, b = first[c], second[c]
            k = inv_m[a] + inv_m[b]
            if k <= 0:
                continue
            n = vec(normal, c)
            now = gap[c] + dot(sub(vec(moved, a), vec(moved, b)), n)
            worst = max(worst, floor[c] - now)
            new = max(push[r] + (floor[c] - now) / k, 0.0)
            dp = new - push[r]
            push[r] = new
            for d in range(3):
                moved[a, d] += inv_m[a] * dp * n[d]
                moved[b, d] -= inv_m[b] * dp * n[d]
        done = s + 1
        if worst <= tol:
            break
    for r in range(count):
        c = rows[r]
        for body in (first[c], second[c]):
            if inv_m[body] > 0:
                for d in range(3):
                    x[body, d] += moved[body, d]
                    moved[body, d] = 0.0
    return done
