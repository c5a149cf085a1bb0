"""A dense step: every contact of the step solved at once (time-stepping contact dynamics), for
beds and dense flows where events would cascade.

Each contact gets a target normal velocity for after the step. An impact (approaching faster than
``rest_speed``, touching or closing its gap within the step) rebounds with its restitution,
Newton's law e u_n; any other contact closes its gap within the step but not more
(−gap/dt; 0 when touching). Impulses: normal >= 0, tangential in the Coulomb cone; projected
Gauss–Seidel sweeps over the contacts in the record's order (compiled, ``impulses.sweep``),
started from the previous step's impulses (``ContactMemory``), at most ``dense_sweeps`` sweeps
(20 × as many without any). An impact that happens at time t_c inside the step moves its bodies
as the event solution does: before t_c at the old velocity, after it at the new one
(x_end = x0 + v_new dt − (v_new − v_old) t_c, with t_c for a body in several contacts their
times weighted by their impulses, 0 for a touching one), so an isolated impact ends where the
time-ordered solution ends, with its velocity, and no body moves further than its velocity
change allows. Deposition, the energy check and rolling friction as in a resting solve.
"""
from __future__ import annotations

import numpy as np

from . import jit
from .search import wall_arrays
from .settings import COLD_SWEEPS, ENERGY_TOL, SWEEP_TOL
from .stats import CLAMPS, PAIR, RESTING, SWEEPS, WALL


def dense_step(bodies, record, warm_n, warm_t, settings, dt, walls, kernels, counters, extra):
    """Solve the contacts of ``record`` at once and move every body to the end of the step.
    ``warm_n`` (m,), ``warm_t`` (m, 3): the remembered impulses. Returns the contacts' impulses
    (m,) and (m, 3) (N s, on ``first``)."""
    impulses = kernels.impulses
    n, m = len(bodies.radius) - 1, len(record)
    first, second, triangle = record.first, record.second, record.triangle
    rows = np.arange(m)
    rows = rows[~kernels.narrow.parallel_duplicates(rows, first, triangle, record.gap, record.normal, bodies.radius)]
    wall = triangle >= 0
    r_first = bodies.radius[first]
    r_second = np.where(wall, 0.0, bodies.radius[second])
    deposition = wall_arrays(walls)[9]
    changed = np.zeros(n + 1, np.int64)
    kernels.deposition.deposit_touching(rows, record.gap, r_first, bodies.kernel_tuple(), (first, second, triangle),
                                        deposition, changed, counters)
    v, w, inv_m, inv_i = bodies.v, bodies.w, bodies.inv_m, bodies.inv_i
    normal, gap = record.normal, record.gap
    touching, hits, target, hit_time, closing_speed = targets(bodies, record, rows, r_first, r_second, settings, dt)
    lam_n, lam_t, remembered, members, driven = solve_start(bodies, record, rows, warm_n, warm_t, walls)
    v0, w0 = v.copy(), w.copy()
    energy = impulses.kinetic_energy(members, inv_m, inv_i, v, w)
    if remembered:
        impulses.warm_start(rows, first, second, normal, r_first, r_second, record.friction, inv_m, inv_i, v, w,
                            lam_n, lam_t)
    budget = settings.dense_sweeps if remembered else COLD_SWEEPS * settings.dense_sweeps
    scale = max(closing_speed, settings.rest_speed, 1e-300)
    tol = SWEEP_TOL * settings.rest_speed if settings.rest_speed > 0 else 1e-12 * scale
    sweeps = impulses.sweep(rows, first, second, normal, r_first, r_second, record.wall_velocity, target,
                            record.friction, inv_m, inv_i, v, w, lam_n, lam_t, budget, tol)
    if not driven and impulses.kinetic_energy(members, inv_m, inv_i, v, w) > energy * (1 + ENERGY_TOL) + 1e-300:
        # Newton's law over simultaneous contacts can make energy: solve inelastically instead
        counters[CLAMPS] += 1
        v[:], w[:] = v0, w0
        lam_n[:], lam_t[:] = 0.0, 0.0
        target = -np.maximum(gap, 0.0) / dt
        hit_time[:] = 0.0
        sweeps += impulses.sweep(rows, first, second, normal, r_first, r_second, record.wall_velocity, target,
                                 record.friction, inv_m, inv_i, v, w, lam_n, lam_t, COLD_SWEEPS * settings.dense_sweeps,
                                 tol)
        impulses.limit_energy(members, inv_m, inv_i, v, w, v0, w0, energy, ENERGY_TOL)
    finish(bodies, record, rows, lam_n, lam_t, v0, touching, hits, hit_time, dt, sweeps, counters, extra,
           wall_arrays(walls)[6])
    return lam_n, lam_t


def solve_start(bodies, record, rows, warm_n, warm_t, walls) -> tuple:
    """The contacts' impulses to start the solve of ``rows`` from, (m,) and (m, 3): the remembered
    ``warm_n``, ``warm_t`` on ``rows``, 0 on the others; whether any is remembered; the particles
    in ``rows`` (ascending); whether any contact of ``rows`` is driven (a prescribed body or a
    moving wall: it may put energy in). Compiled: ``step_arrays.solve_start``."""
    wall_drives = walls.drives if walls is not None else np.zeros(0, bool)
    return jit.kernels().step_arrays.solve_start(rows, record.first, record.second, record.triangle, warm_n, warm_t,
                                                 bodies.driven, wall_drives, len(bodies.radius) - 1)


def targets(bodies, record, rows, r_first, r_second, settings, dt) -> tuple:
    """Per contact of ``rows`` (the others left False and 0): whether it touches, whether it is an
    impact, the normal velocity it is driven to (m/s), the time inside the step its impact
    happens (s; 0 for a touching one and for the others); and the largest closing speed over
    ``rows`` at the step's start (m/s). Compiled: ``step_arrays.targets``."""
    return jit.kernels().step_arrays.targets(rows, record.first, record.second, record.normal, record.gap,
                                             record.time, record.restitution, record.wall_velocity, r_first,
                                             r_second, bodies.v, bodies.w, settings.rest_speed, dt)


def finish(bodies, record, rows, lam_n, lam_t, v0, touching, hits, hit_time, dt, sweeps, counters, extra, wall_omega,
           to_owners=None) -> None:
    """After the solve of ``rows``: rolling friction, every body moved to the step's end, the counts.
    ``wall_omega``: the walls' angular velocities (triangles, 3); ``to_owners`` (on several ranks):
    sums the ghost rows of per-body arrays on their owners."""
    n, compiled = len(bodies.radius) - 1, jit.kernels().step_arrays
    # each body's velocity changed at the impulse-weighted time of its contacts (0 touching, t_c
    # for an impact inside the step): before it the body moved at its old velocity
    weight, late = compiled.change_times(rows, record.first, record.second, lam_n, lam_t, hit_time, n)
    if to_owners is not None:
        to_owners(weight[:n], late[:n])
    contacts = (record.first, record.triangle, record.normal, record.wall_velocity, record.friction,
                record.rolling_friction)
    pair, wall, resting = compiled.move_to_end(rows, contacts, lam_n, lam_t, touching, hits, weight, late,
                                               (bodies.x, bodies.v, bodies.w, bodies.inv_m, bodies.inv_i, bodies.radius),
                                               v0, wall_omega, dt)
    counters[PAIR] += pair
    counters[WALL] += wall
    counters[RESTING] += resting
    counters[SWEEPS] += sweeps
    extra.update(dense_steps=1, dense_contacts=len(rows))
