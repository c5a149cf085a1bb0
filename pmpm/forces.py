"""Body forces on the particles: gravity with buoyancy, and the field forces of paper eq. 9-10.

Pure functions of the particle arrays; on one rank, for every particle; where ranks own particles,
each for its own, with ghost copies of the others' within the cutoff.

Eq. 9, between particles i and j at centre distance R (within ``cutoff``)::

    F_i = G_p M_i^n1 M_j^n2 / R^n3   along the line of centres, towards j when G_p > 0

applied as an equal and opposite pair (the term with M_j^n1 M_i^n2 is not used for F_j, so that
momentum is conserved exactly even when n1 != n2). Eq. 10, from each wall boundary at distance R_i
(the nearest of its triangles, within ``cutoff``)::

    F_iw = G_w M_i^n4 / R_i^n5   along the wall normal, towards the wall when G_w > 0
"""
from __future__ import annotations

import numpy as np

from .arrays import kd_tree, sum_rows
from .collisions import Walls, closest_points_on_triangles
from .halo import Halo
from .ownership import Partition
from .particles import ParticleState


def gravity_buoyancy(state: ParticleState, gravity, fluid_density: float) -> np.ndarray:
    """(n, 3) gravity less buoyancy, (ρ_p − ρ_f) V g (N); ``fluid_density`` 0 without a fluid."""
    excess = (state.density - fluid_density) * state.volume
    return excess[:, None] * np.asarray(gravity, float)[None, :]


def field_forces(state: ParticleState, walls: Walls | None, G_p: float, n1: float, n2: float, n3: float,
                 G_w: float, n4: float, n5: float, cutoff: float) -> np.ndarray:
    """(n, 3) field forces (N) of eq. 9 (pairs closer than ``cutoff``) and eq. 10 (walls)."""
    n = len(state)
    force = np.zeros((n, 3))
    if n == 0:
        return force
    mass = state.mass
    if G_p != 0.0 and n > 1:
        pairs = kd_tree(state.x).query_pairs(cutoff, output_type="ndarray")
        if len(pairs):
            i, j = pairs[:, 0], pairs[:, 1]
            d = state.x[j] - state.x[i]
            R = np.linalg.norm(d, axis=1)
            ok = R > 0
            i, j, d, R = i[ok], j[ok], d[ok], R[ok]
            size = G_p * mass[i] ** n1 * mass[j] ** n2 / R ** n3
            f = (size / R)[:, None] * d  # on i, towards j when G_p > 0
            force += sum_rows(i, f, n) - sum_rows(j, f, n)
    if G_w != 0.0 and walls is not None and len(walls):
        force += wall_field_forces(state.x, mass, walls, G_w, n4, n5, cutoff)
    return force


def wall_field_forces(x, mass, walls: Walls, G_w, n4, n5, cutoff) -> np.ndarray:
    """(n, 3) eq. 10: one term per wall boundary, from its nearest triangle within ``cutoff``.

    The direction is from the centre to the nearest point of the wall: the wall normal over a
    face, and continuous across edges and corners of one boundary.
    """
    n = len(x)
    p, k = walls.near(x, cutoff)
    if len(p) == 0:
        return np.zeros((n, 3))
    q, _ = closest_points_on_triangles(x[p], walls.a[k], walls.b[k], walls.c[k])
    towards = q - x[p]
    R = np.linalg.norm(towards, axis=1)
    # keep, for each (particle, boundary), its nearest triangle
    order = np.lexsort((R, walls.boundary[k], p))
    p, k, towards, R = p[order], k[order], towards[order], R[order]
    key = np.column_stack([p, walls.boundary[k]])
    first = np.ones(len(p), bool)
    first[1:] = np.any(key[1:] != key[:-1], axis=1)
    keep = first & (R <= cutoff) & (R > 0)
    p, towards, R = p[keep], towards[keep], R[keep]
    size = G_w * mass[p] ** n4 / R ** n5
    return sum_rows(p, (size / R)[:, None] * towards, n)


def field_forces_of_case(state: ParticleState, walls: Walls | None, section, comm=None,
                         partition: Partition | None = None) -> np.ndarray:
    """Eq. 9-10 with the [field_forces] section's constants (cutoff: 5 mean diameters by default).

    With ``partition`` (collective over ``comm``): ``state`` holds the particles this rank owns, and
    the pairs reach the particles of other ranks within the cutoff through ghost copies of them
    (``halo.Halo``); the default cutoff is from the mean diameter over every rank."""
    if partition is None:
        if len(state) == 0:
            return np.zeros((0, 3))
        cutoff = section.cutoff if section.cutoff is not None else 5.0 * 2.0 * float(np.mean(state.radius))
        return field_forces(state, walls, section.G_p, section.n1, section.n2, section.n3,
                            section.G_w, section.n4, section.n5, cutoff)
    count, total = comm.allreduce(np.array([len(state), state.radius.sum()]))
    cutoff = section.cutoff if section.cutoff is not None else 5.0 * 2.0 * total / max(count, 1.0)
    halo, local = Halo.build(comm, partition, state, cutoff * (1 + 1e-9))
    return field_forces(local, walls, section.G_p, section.n1, section.n2, section.n3, section.G_w, section.n4,
                        section.n5, cutoff)[halo.owned]
