"""Checks of new particles: initial ones that are outside the domain or overlap (a CaseError), and
injected ones that would overlap a particle already there (skipped)."""
from __future__ import annotations

from itertools import chain

import numpy as np

from ..arrays import kd_tree
from ..errors import CaseError
from ..particles import ParticleState
from .walls import Walls, wall_distances


def check_initial_particles(case, new, inside, walls: Walls | None) -> None:
    """Refuse initial particles outside the domain, overlapping each other or a wall (CaseError)."""
    name = case.path.name
    outside = np.flatnonzero(~np.asarray(inside, bool))
    if len(outside):
        i = outside[0]
        raise CaseError(f"{name}: particle {i}: centre {fmt(new.x[i])} is outside the domain")
    n = len(new)
    if n > 1:
        tree = kd_tree(new.x)
        pairs = tree.query_pairs(2 * float(new.radius.max()), output_type="ndarray")
        dist = np.linalg.norm(new.x[pairs[:, 0]] - new.x[pairs[:, 1]], axis=1)
        bad = dist < (new.radius[pairs[:, 0]] + new.radius[pairs[:, 1]]) * (1 - 1e-9)
        if bad.any():
            i, j = pairs[bad][np.argmin(pairs[bad].max(1))]
            i, j = sorted((int(i), int(j)))
            raise CaseError(f"{name}: particle {j} (centre {fmt(new.x[j])}, radius {new.radius[j]:g}) "
                            f"overlaps particle {i} (centre {fmt(new.x[i])}, radius {new.radius[i]:g})")
    if walls is not None and len(walls) and n:
        distance = wall_distances(new.x, walls, new.radius)
        bad = np.flatnonzero(distance < new.radius * (1 - 1e-9))
        if len(bad):
            i = bad[0]
            raise CaseError(f"{name}: particle {i}: centre {fmt(new.x[i])} is {distance[i]:.6g} m from a wall, "
                            f"less than its radius {new.radius[i]:g} m")


def overlaps_existing(state: ParticleState, new) -> np.ndarray:
    """(len(new),) bool: new particles that overlap a particle of ``state`` or an earlier new one
    that is kept."""
    m = len(new)
    bad = np.zeros(m, bool)
    if m == 0:
        return bad
    if len(state):
        found = kd_tree(state.x).query_ball_point(new.x, float(state.radius.max()) + new.radius)
        i, k = flatten(found)
        close = np.linalg.norm(state.x[k] - new.x[i], axis=1) < (state.radius[k] + new.radius[i]) * (1 - 1e-9)
        bad[i[close]] = True
    if m > 1:
        pairs = kd_tree(new.x).query_pairs(2 * float(new.radius.max()), output_type="ndarray")
        pairs = np.sort(pairs, axis=1)
        d = np.linalg.norm(new.x[pairs[:, 0]] - new.x[pairs[:, 1]], axis=1)
        pairs = pairs[d < (new.radius[pairs[:, 0]] + new.radius[pairs[:, 1]]) * (1 - 1e-9)]
        for i, j in pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]:  # the few overlapping pairs, in order
            if not bad[i]:
                bad[j] = True
    return bad


def flatten(found) -> tuple[np.ndarray, np.ndarray]:
    """A k-d tree's per-point lists of neighbours as (point, neighbour) index arrays."""
    sizes = np.fromiter(map(len, found), np.int64, len(found))
    row = np.repeat(np.arange(len(found)), sizes)
    return row, np.fromiter(chain.from_iterable(found), np.int64, int(sizes.sum()))


def fmt(vector) -> str:
    return "(" + ", ".join(f"{float(v):.6g}" for v in vector) + ")"
