"""Broad search: the contacts that may act within a step, as a ``ContactRecord``.

Particle pairs come from a cell list of the centres (every pair closer than r_i + r_j + reach;
``cell_list``), wall candidates from the walls' grid (``Walls.near``: boxes and bounding spheres
of the triangles, grown by how far each moves in the step); the compiled narrow phase
(``narrow``) keeps those whose gap is within reach and computes gap, normal and contact time.
``reach`` bounds how far two bodies can close in a step: twice the largest speed × dt between
particles, once it (plus the wall's own travel) for a wall; a particle that becomes faster
within the step makes the solver search again
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


def candidate_pairs(x: np.ndarray, radius: np.ndarray, reach: float, cell_list,
                    around: np.ndarray | None = None) -> np.ndarray:
    """(k, 2) int64 pairs i < j, sorted, of centres closer than r_i + r_j + ``reach`` (m), by the
    compiled cell list; with ``around`` (indices), only the pairs with one of them."""
    chosen = np.ones(len(x), np.bool_)
    if around is not None:
        chosen[:] = False
        chosen[around] = True
    return cell_list.close_pairs(np.ascontiguousarray(x, float), np.ascontiguousarray(radius, float), float(reach),
                                 chosen)


def find_contacts(bodies, walls: Walls | None, dt: float, reach: float, restitution: float, friction: float,
                  kernels, around: np.ndarray | None = None, dense_contacts: int = 0) -> tuple[ContactRecord, bool]:
    """The step's contacts (see the module's docstring), and whether the step is dense: at least
    ``dense_contacts`` (> 0) of them can act (touching, or closing within ``dt`` at the relative
    speed of the centres); a dense step's record holds only those. With ``around`` (particle
    indices), only the contacts of those particles.

    Parameters
    ----------
    bodies : solver.Bodies at the step's start (rows 0..n−1 particles, row n the world).
    walls : the walls at the step's start, or None.
    dt : s; reach : m, how far two particles can close in the step.
    restitution, friction : particle–particle coefficients.
    kernels : the compiled modules (``jit.kernels()``).
    """
    n = len(bodies.radius) - 1
    x, v, radius, free = bodies.x, bodies.v, bodies.radius, bodies.free
    narrow = kernels.narrow
    pairs = candidate_pairs(x[:n], radius[:n], reach, kernels.cell_list, around)
    keep, acts, normal, gap, time = narrow.pair_contacts(pairs[:, 0], pairs[:, 1], x, v, radius, free, reach, dt)
    pair_part = (keep, acts, pairs, normal, gap, time)
    wall_part = None
    mobile = np.flatnonzero(free[:n])
    if around is not None:
        mobile = np.intersect1d(mobile, around)
    if walls is not None and len(walls) and len(mobile):
        travel = walls.travel(dt)
        p, tri = walls.near(x[mobile], radius[mobile] + 0.5 * reach, extra=travel)
        p = mobile[p]
        wall_part = (p, tri) + narrow.wall_contacts(p, tri, x, v, radius, wall_arrays(walls), travel, 0.5 * reach, dt)
    dense = 0 < dense_contacts <= int(acts.sum()) + (int(wall_part[3].sum()) if wall_part is not None else 0)
    # a dense step needs only the contacts that can act; an event step all within reach
    take = np.flatnonzero(acts if dense else keep)
    k = len(take)
    parts = [ContactRecord(pairs[take, 0], pairs[take, 1], np.full(k, -1), normal[take], gap[take], np.ones(k, bool),
                           time[take], np.zeros((k, 3)), np.full(k, restitution), np.full(k, friction), np.zeros(k))]
    if wall_part is not None:
        p, tri, keep, acts, normal, gap, face, u_wall, time = wall_part
        take = np.flatnonzero(acts if dense else keep)
        p, tri = p[take], tri[take]
        parts.append(ContactRecord(p, np.full(len(p), n), tri, normal[take], gap[take], face[take], time[take],
                                   u_wall[take], walls.restitution[tri], walls.friction[tri],
                                   walls.rolling_friction[tri]))
    return ContactRecord.concatenate(parts), dense
