"""Broad search: the contacts that may act within a step, as a ``ContactRecord``.

Particle pairs come from a cell list of the centres (every pair closer than r_i + r_j + reach;
``cell_list``; where the step is likely dense (the step before was), first those closer than
r_i + r_j + each one's travel in the step, which hold every pair that can act), wall candidates
from the walls' grid (``Walls.near``: boxes and bounding spheres of the triangles, grown by how
far each moves in the step); the compiled narrow phase (``narrow``) keeps those whose gap is
within reach and computes gap, normal and contact time. ``reach`` bounds how far two bodies can
close in a step: twice the largest speed × dt between particles, once it (plus the wall's own
travel) for a wall; a particle that becomes faster within the step makes the solver search again
(``solver.advance_with_collisions``).
"""
from __future__ import annotations

import numpy as np

from .record import ContactRecord
from .walls import Walls


def wall_arrays(walls: Walls | None) -> tuple:
    """The walls' arrays in the order the compiled kernels take them (``narrow``); empty ones
    without walls."""
    return walls.kernel_arrays if walls is not None and len(walls) else no_walls()


def no_walls() -> tuple:
    z3 = np.zeros((0, 3))
    zb = np.zeros(0, np.bool_)
    return (z3, z3, z3, z3, z3, z3, z3, zb, zb, zb)


def travel_of(speed, dt: float, reach: float):
    """How far a body at ``speed`` (m/s; array or scalar) goes in ``dt`` (a hair more), at most
    half the step's ``reach``: the search by each one's travel of a step that may be dense
    (``step_arrays.travels``: of each body's velocity, compiled)."""
    return np.minimum(np.asarray(speed) * dt * (1 + 1e-9), 0.5 * reach)


def candidate_pairs(x: np.ndarray, radius: np.ndarray, reach, cell_list,
                    around: np.ndarray | None = None) -> np.ndarray:
    """(k, 2) int64 pairs i < j, sorted, of centres closer than r_i + r_j + ``reach`` (m; or
    reach_i + reach_j, one per particle), by the compiled cell list; with ``around`` (indices),
    only the pairs with one of them."""
    chosen = np.ones(len(x), np.bool_)
    if around is not None:
        chosen[:] = False
        chosen[around] = True
    each = np.broadcast_to(np.asarray(reach, float), (len(x),)) if np.ndim(reach) else np.full(len(x), 0.5 * reach)
    return cell_list.close_pairs(np.ascontiguousarray(x, float), np.ascontiguousarray(radius, float),
                                 np.ascontiguousarray(each), chosen)


def pair_contacts(bodies, search_reach, reach: float, dt: float, kernels, around, owned) -> tuple:
    """The particle pairs of ``find_contacts``: candidates closer than r_i + r_j + ``search_reach``
    (m, or one reach per particle each side, ``candidate_pairs``), through the narrow phase (kept
    within ``reach``); returns pairs, keep, acts, counted (acts on the owner of ``first``),
    normal, gap, time."""
    n = len(bodies.radius) - 1
    if owned is not None and around is None:   # a pair of two ghosts is another rank's
        around = np.flatnonzero(owned)
    pairs = candidate_pairs(bodies.x[:n], bodies.radius[:n], search_reach, kernels.cell_list, around)
    keep, acts, normal, gap, time = kernels.narrow.pair_contacts(pairs[:, 0], pairs[:, 1], bodies.x, bodies.v,
                                                                 bodies.radius, bodies.free, reach, dt)
    counted = acts
    if owned is not None:
        mine = owned[pairs[:, 0]] | owned[pairs[:, 1]]
        keep, acts, counted = keep & mine, acts & mine, acts & owned[pairs[:, 0]]
    return pairs, keep, acts, counted, normal, gap, time


def find_contacts(bodies, walls: Walls | None, dt: float, reach: float, restitution: float, friction: float,
                  kernels, around: np.ndarray | None = None, dense_contacts: int = 0, owned: np.ndarray | None = None,
                  comm=None, dense_likely: bool = True) -> tuple[ContactRecord, bool, int]:
    """The step's contacts (see the module's docstring), whether the step is dense: at least
    ``dense_contacts`` (> 0) of them can act (touching, or closing within ``dt`` at the relative
    speed of the centres), and how many can act; a dense step's record holds only those. With
    ``around`` (particle indices), only the contacts of those particles.

    Parameters
    ----------
    bodies : solver.Bodies at the step's start (rows 0..n−1 particles, row n the world).
    walls : the walls at the step's start, or None.
    dt : s; reach : m, how far two particles can close in the step.
    restitution, friction : particle–particle coefficients.
    kernels : the compiled modules (``jit.kernels()``).
    owned : (n,) bool, on a rank of several (``subdomains``): only the contacts of these particles
        are kept, and the contacts that can act are counted once, by the owner of ``first``, and
        summed over ``comm`` (collective then), so every rank takes the same dense decision.
    dense_likely : whether the step is expected to be dense (the step before was): if not, the
        pairs are searched within the reach at once, not by travel first and then again. The
        same record and decision either way: the search by travel finds every pair that can act.
    """
    n = len(bodies.radius) - 1
    x, v, radius, free = bodies.x, bodies.v, bodies.radius, bodies.free
    narrow = kernels.narrow
    # A pair can act only if its gap closes within dt at the relative speed of the centres, at most
    # the sum of their speeds: searched by each particle's own travel first, the pairs that can
    # act are all found (the dense step needs no others) among far fewer than within the reach of
    # the fastest particle. An event step needs every pair within reach: searched again then, or
    # at once where the step before was not dense either.
    by_travel = dense_contacts > 0 and dense_likely
    travel = kernels.step_arrays.travels(v[:n], None, dt, reach) if by_travel else reach
    pairs, keep, acts, counted, normal, gap, time = pair_contacts(bodies, travel, reach, dt, kernels, around, owned)
    wall_part = None
    mobile = np.flatnonzero(free[:n])
    if around is not None:
        mobile = np.intersect1d(mobile, around)
    if owned is not None:
        mobile = mobile[owned[mobile]]
    if walls is not None and len(walls) and len(mobile):
        wall_travel = walls.travel(dt)
        p, tri = walls.near(x[mobile], radius[mobile] + 0.5 * reach, extra=wall_travel)
        p = mobile[p]
        wall_part = (p, tri) + narrow.wall_contacts(p, tri, x, v, radius, wall_arrays(walls), wall_travel,
                                                    0.5 * reach, dt)
    acting = int(counted.sum()) + (int(wall_part[3].sum()) if wall_part is not None else 0)
    if comm is not None:
        acting = comm.allreduce(acting)
    dense = 0 < dense_contacts <= acting
    if not dense and by_travel:
        pairs, keep, acts, counted, normal, gap, time = pair_contacts(bodies, reach, reach, dt, kernels, around, owned)
    # a dense step needs only the contacts that can act; an event step all within reach
    pair_rows = np.flatnonzero(acts if dense else keep)
    none = np.zeros(0, np.int64)
    p, tri, wall_keep, wall_acts, wall_normal, wall_gap, face, u_wall, wall_time = wall_part or (
        none, none, np.zeros(0, bool), np.zeros(0, bool), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool),
        np.zeros((0, 3)), np.zeros(0))
    wall_rows = np.flatnonzero(wall_acts if dense else wall_keep)
    coefficients = (walls.restitution, walls.friction, walls.rolling_friction) if wall_part else (np.zeros(0),) * 3
    # both parts come sorted (pairs by (i, j), walls by particle then triangle): merged in one pass
    record = ContactRecord(*kernels.step_arrays.merged_record(
        pair_rows, pairs, normal, gap, time, float(restitution), float(friction), wall_rows, p, tri, wall_normal,
        wall_gap, face, wall_time, u_wall, *coefficients, n))
    return record, dense, acting
