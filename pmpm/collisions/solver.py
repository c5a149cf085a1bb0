"""One step of the particles with their contacts: ``advance_with_collisions``.

Every regime takes the same path: broad search → contact record (arrays) → compiled solve → the
positions at the end of the step with overlaps removed. The solve is one of two compiled
schedules over the same record, chosen by how many contacts can act in the step:

- an event step (fewer than ``dense_contacts``): the resting contacts solved together at the
  start, then impacts in time order with exact contact times (eq. 5-7), slow ones settling the
  resting contacts around them (``events``);
- a dense step (a bed, a hopper): every contact at once by sweeps, impacts with their restitution
  (``dense``).

Both start from the impulses the contacts had in the previous step (``ContactMemory``), so a
resting pack converges across steps and stays at rest. Velocities are constant inside a step: the
caller has applied gravity, drag and field forces as a velocity update before.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import jit
from .dense import dense_step
from .record import ContactMemory
from .search import find_contacts, wall_arrays
from .settings import (MAX_SEARCHES, OVERLAP_TOL, SEARCH_SLACK, SEPARATION_SWEEPS, SWEEP_TOL,
                       CollisionSettings)
from .stats import EXCEEDED, as_dict, new_counters
from .walls import Walls
from ..particles import FIXED, FREE, PRESCRIBED, ParticleState, fastest


@dataclass
class Bodies:
    """The step's working copy of the particles, plus the world (row n: walls) (SI).

    x, v, w : (n + 1, 3) positions, velocities, angular velocities (fixed and deposited at rest).
    inv_m, inv_i : (n + 1,) 1/m, 1/I; 0 for infinite mass (fixed, prescribed, deposited, world).
    radius : (n + 1,) (0 for the world); free : (n + 1,) bool, responds to impulses;
    deposited : (n + 1,) bool; driven : (n + 1,) bool, prescribed and moving.
    clock : (n + 1,) s, the time each body's x refers to; stamp : (n + 1,) int64, event counters.
    """

    x: np.ndarray
    v: np.ndarray
    w: np.ndarray
    inv_m: np.ndarray
    inv_i: np.ndarray
    radius: np.ndarray
    free: np.ndarray
    deposited: np.ndarray
    driven: np.ndarray
    clock: np.ndarray
    stamp: np.ndarray

    @classmethod
    def of(cls, state: ParticleState) -> "Bodies":
        stays = (state.motion == FIXED) | state.deposited
        prescribed = (state.motion == PRESCRIBED) & ~state.deposited
        x, v, w, inv_m, inv_i, radius, free, driven = jit.kernels().step_arrays.working_copy(
            state.x, state.v, state.omega, state.radius, state.mass, state.movable, stays, prescribed)
        n = len(state)
        return cls(x, v, w, inv_m, inv_i, radius, free, np.append(state.deposited, False), driven, np.zeros(n + 1),
                   np.zeros(n + 1, np.int64))

    def copy(self) -> "Bodies":
        return Bodies(*(np.array(value) for value in self.arrays()[:9]), self.clock.copy(), self.stamp.copy())

    def arrays(self) -> tuple:
        return (self.x, self.v, self.w, self.inv_m, self.inv_i, self.radius, self.free, self.deposited, self.driven,
                self.clock, self.stamp)

    def top_speed(self) -> float:
        """As ``ParticleState.top_speed``, of the working copy (velocities changed in the step)."""
        return fastest(self.v, self.free | self.driven)

    def kernel_tuple(self) -> tuple:
        """The arrays as the compiled events take them."""
        return (self.x, self.v, self.w, self.inv_m, self.inv_i, self.radius, self.free, self.deposited, self.clock,
                self.stamp)


@dataclass
class ContactStep:
    """What a step returns besides the particles it moved.

    stats : dict of counts (``stats.NAMES`` and ``stats.EXTRA``);
    memory : the contacts' impulses for the next step's warm start;
    walls : the walls after the step (rigid walls moved); the walls passed in are unchanged.
    """

    stats: dict
    memory: ContactMemory
    walls: Walls | None


def advance_with_collisions(state: ParticleState, walls: Walls | None, dt: float, settings: CollisionSettings,
                            memory: ContactMemory | None = None, speed: float | None = None,
                            population: int | None = None) -> ContactStep:
    """Move every particle over ``dt`` with its contacts resolved (see the module's docstring).

    ``state`` is updated in place (x, v, omega, deposited). Free particles move with constant
    velocity between contacts; fixed and deposited ones stay put, prescribed ones keep their
    velocity (all three have infinite mass); rigid walls move by their motion over the step.

    Rolling friction: at a resting, rolling contact with a wall (normal impulse J_n over the step)
    a torque μ_r N r opposes rolling; with the rolling constraint this slows the rolling velocity
    by (5/7) μ_r J_n / m (on a flat floor: deceleration (5/7) μ_r g) and the spin with it.

    ``speed`` (m/s) and ``population``: the search's speed and the particle count the event budget
    is for, where ``state`` is a part of the particles (``subdomains``: the ranks' contact
    clusters gathered); by default this state's.
    """
    dt = float(dt)
    memory = ContactMemory.empty() if memory is None else memory
    walls_after = walls.moved(dt) if walls is not None else None
    counters, extra = new_counters(), {}
    n = len(state)
    if n == 0:
        return ContactStep(as_dict(counters, extra), memory, walls_after)
    kernels = jit.kernels()
    start = Bodies.of(state)
    walls = walls if walls is not None and len(walls) and start.free.any() else None
    wall_speed = float(walls.top_speed.max()) if walls is not None else 0.0
    # impacts can make a particle faster than any was (a light one hit by a heavy one, a paddle)
    if speed is None:
        speed = max(SEARCH_SLACK * state.top_speed(), settings.rest_speed, 2.0 * wall_speed)
    for attempt in range(MAX_SEARCHES):
        last = attempt == MAX_SEARCHES - 1
        bodies = start.copy()
        exceeded = counters[EXCEEDED]
        counters[:] = 0
        counters[EXCEEDED] = exceeded
        record, dense, _ = find_contacts(bodies, walls, dt, 2.0 * speed * dt, settings.restitution, settings.friction,
                                      kernels, dense_contacts=settings.dense_contacts,
                                      dense_likely=len(memory) >= settings.dense_contacts)
        warm_n, warm_t = memory.recall(record, state.id)
        extra["contacts"] = len(record)
        if dense:
            lam_n, lam_t = dense_step(bodies, record, warm_n, warm_t, settings, dt, walls, kernels, counters, extra)
            break
        lam_n, lam_t = np.zeros(len(record)), np.zeros((len(record), 3))
        top = event_step(bodies, record, warm_n, warm_t, lam_n, lam_t, settings, dt, np.inf if last else speed,
                         walls, kernels, counters, population)
        if top <= speed or last:
            break
        counters[EXCEEDED] += 1
        speed = SEARCH_SLACK * top
    remove_overlaps(bodies, record, walls_after, kernels, extra, 2.0 * speed * dt, thorough=not dense)
    state.x[:] = bodies.x[:n]
    free = state.motion == FREE  # deposited ones included: they now rest
    state.v[free] = bodies.v[:n][free]
    state.omega[:] = bodies.w[:n]
    state.deposited[:] = bodies.deposited[:n]
    # a dense step remembers every contact it solved (a bed's unloaded ones too: the next step's
    # start), an event step the contacts that pushed
    memory = ContactMemory.remember(record, state.id, lam_n, lam_t, np.ones(len(record), bool) if dense else None)
    return ContactStep(as_dict(counters, extra), memory, walls_after)


def event_step(bodies, record, warm_n, warm_t, lam_n, lam_t, settings, dt, speed_bound, walls, kernels,
               counters, population: int | None = None) -> float:
    """The event schedule (``events.run_events``) over the record; the resting impulses of the step
    accumulate in ``lam_n``, ``lam_t``. Returns the largest speed reached (the step is unfinished
    if it exceeds ``speed_bound``)."""
    n = len(bodies.radius) - 1
    start, adjacency = record.adjacency(n)
    driven = bodies.driven[record.first] | bodies.driven[record.second]
    if walls is not None:
        wall = record.triangle >= 0
        driven[wall] |= walls.drives[record.triangle[wall]]
    contacts = (record.first, record.second, record.triangle, record.friction, record.rolling_friction,
                record.restitution, driven, start, adjacency)
    scale = max(settings.rest_speed, bodies.top_speed(), 1e-300)
    tol = SWEEP_TOL * settings.rest_speed if settings.rest_speed > 0 else 1e-12 * scale
    max_events = max(settings.max_events_per_particle * (n if population is None else population), settings.min_events)
    return float(kernels.events.run_events(bodies.kernel_tuple(), contacts, wall_arrays(walls),
                                           (warm_n, warm_t, lam_n, lam_t), dt, settings.rest_speed, max_events,
                                           speed_bound, settings.resting_sweeps, settings.settle_sweeps, tol,
                                           counters))


def remove_overlaps(bodies, record, walls_after, kernels, extra, searched: float, thorough: bool) -> None:
    """Move apart (positions only) the contacts that overlap at the end of the step by more than
    ``OVERLAP_TOL`` (r_i + r_j), without pushing the contacts of the spheres moved into new
    overlaps.

    ``thorough`` (an event step: few contacts): sweeps until done, and if a sphere moved further
    than a quarter of the step's search reached (``searched``, m), the contacts of the spheres
    moved are searched again and the removal repeated (3 passes in all): a sphere released deep
    into a wall or into other spheres is separated in one step. Otherwise (a dense step: a pack
    creeps by what its budgeted sweeps left) a few sweeps over the contacts of the spheres that
    overlap; what is left goes to the next step, whose search lists every contact touching."""
    walls = wall_arrays(walls_after)
    removed = 0
    for attempt in range(3):
        if len(record) == 0:
            break
        gap, normal, front = kernels.narrow.end_gaps(record.first, record.second, record.triangle, bodies.x,
                                                     bodies.radius, walls)
        # the overlaps, and the contacts that moving them apart could close (the deepest overlap
        # bounds how far a sphere moves)
        overlaps, rows, floor, smallest = kernels.step_arrays.overlap_rows(
            record.first, record.second, bodies.radius, gap, front, OVERLAP_TOL, thorough)
        if overlaps == 0:
            break
        removed += overlaps
        before = bodies.x.copy() if thorough else None
        kernels.impulses.separate(rows, record.first, record.second, normal, gap, floor, bodies.inv_m, bodies.x,
                                  SEPARATION_SWEEPS if thorough else SEPARATION_SWEEPS // 5,
                                  0.5 * OVERLAP_TOL * float(smallest))
        if not thorough:
            break
        shift = np.sqrt(((bodies.x - before) ** 2).sum(1))
        moved = float(shift.max())
        if moved <= 0.25 * searched:
            break  # (too little to reach a sphere beyond the contacts searched)
        searched = 2.0 * moved
        record = find_contacts(bodies, walls_after if walls_after is not None and len(walls_after) else None, 0.0,
                               searched, 0.0, 0.0, kernels, around=np.flatnonzero(shift[:-1] > 0))[0]
    extra["overlaps_removed"] = removed


def projected_gauss_seidel(i, j, normal, r_i, r_j, u_wall, target, mu, inv_mass, inv_inertia, v, omega,
                           lam_n, lam_t, sweeps: int, tol: float) -> int:
    """Projected Gauss–Seidel over contacts (``impulses.sweep`` on all of them, in order) until no
    contact changes the velocities by more than ``tol`` (m/s) or ``sweeps`` sweeps are done;
    returns the sweeps made.

    Parameters
    ----------
    i, j : (m,) int, the contact's bodies (rows of ``v``); the normal points towards i.
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
    as_int = lambda a: np.ascontiguousarray(a, np.int64)  # noqa: E731
    as_float = lambda a: np.ascontiguousarray(a, np.float64)  # noqa: E731
    rows = np.arange(len(i), dtype=np.int64)
    return int(jit.kernels().impulses.sweep(rows, as_int(i), as_int(j), as_float(normal), as_float(r_i), as_float(r_j),
                                            as_float(u_wall), as_float(target), as_float(mu), as_float(inv_mass),
                                            as_float(inv_inertia), v, omega, lam_n, lam_t, int(sweeps), float(tol)))


def contact_impulse(u, n, inv_mass, k_t, e, mu) -> tuple[np.ndarray, bool]:
    """Impulse (3,) on body i at one contact and whether it sticks: normal restitution e, Coulomb
    friction μ (the compiled ``impulses.impact``). u: relative contact velocity (i minus j),
    n: unit normal towards i, inv_mass: 1/m_i + 1/m_j, k_t: 1/m_i + r_i²/I_i + 1/m_j + r_j²/I_j."""
    J, sticking = jit.kernels().impulses.impact(tuple(map(float, u)), tuple(map(float, n)), float(inv_mass),
                                                float(k_t), float(e), float(mu))
    return np.array(J), bool(sticking)


def closing_pairs(pairs, x, v, radius, free, reach, horizon, tol) -> np.ndarray:
    """(k,) bool over candidate ``pairs`` (k, 2) of particles: at least one ``free``, centres
    apart, and a gap g = |x_i − x_j| − r_i − r_j with g <= ``reach`` + tol (r_i + r_j) (m) and
    g <= |v_i − v_j| ``horizon`` + tol r_i: it can close within ``horizon`` (s) at the centres'
    relative speed. x, v (n, 3), radius (n,), free (n,) bool."""
    as_float = lambda a: np.ascontiguousarray(a, np.float64)  # noqa: E731
    return jit.kernels().narrow.closing_pairs(np.ascontiguousarray(pairs, np.int64), as_float(x), as_float(v),
                                              as_float(radius), np.ascontiguousarray(free, np.bool_), float(reach),
                                              float(horizon), float(tol))
