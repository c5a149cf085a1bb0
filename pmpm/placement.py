"""Where released particles go: a place in the domain, clear of the walls and of every particle.

A release that cannot take its particle — outside the domain, cutting a wall, overlapping a
particle already there or one placed before it — tries the next of its alternatives (random
injections draw ``injection.RELEASE_ATTEMPTS`` positions per particle, from the seed, so every rank
and every rank count takes the same decision); with none left the particle is dropped. The run
counts what was placed at once, placed after retries, and dropped (summary.json).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .arrays import kd_tree
from .collisions import wall_distances
from .injection import NewParticles
from .parallel import allreduce_sum
from .particles import ParticleState


@dataclass(frozen=True)
class Placement:
    """The particles placed (their positions chosen), and the counts of this placement."""

    placed: NewParticles
    counts: dict


def place_releases(mesh, particles: ParticleState, walls, new: NewParticles) -> Placement:
    """Collective. Each new particle at the first of its positions (the release point, then its
    alternatives) that lies in the domain, clear of ``walls`` (None: no walls to keep clear of) and
    of ``particles`` (every rank's: a rank may hold only its own); among the new ones an earlier particle keeps its place and a later one moves
    on. Counts: ``placed`` (at the first try), ``retried`` (placed at a later one), ``dropped``."""
    n = len(new)
    candidates = np.concatenate([new.x[None], new.other_positions])          # (attempts, n, 3)
    attempts = len(candidates)
    points, radius = candidates.reshape(-1, 3), np.tile(new.radius, attempts)
    usable = np.isfinite(points).all(axis=1)
    usable[usable] = mesh.inside_domain(points[usable])
    if walls is not None and len(walls):
        usable[usable] = wall_distances(points[usable], walls, radius[usable]) >= radius[usable] * (1 - 1e-9)
    clash = overlaps(particles.x, particles.radius, points[usable], radius[usable]) if len(particles) else \
        np.zeros(int(usable.sum()), bool)
    if mesh.comm.size > 1:   # where ranks own particles, each knows its own (replicated: the same everywhere)
        clash = allreduce_sum(mesh.comm, clash.astype(np.int64)) > 0
    usable[usable] = ~clash
    usable = usable.reshape(attempts, n)
    choice = first_usable(usable)
    while True:   # new against new: the later of two overlapping particles moves on (each round
                  # strikes a position off, so this ends)
        placed = np.flatnonzero(choice >= 0)
        x = candidates[choice[placed], placed]
        pairs = kd_tree(x).query_pairs(2 * float(new.radius.max(initial=0.0)), output_type="ndarray") \
            if len(placed) > 1 else np.zeros((0, 2), np.int64)
        i, j = placed[np.sort(pairs, axis=1).T] if len(pairs) else (np.zeros(0, np.int64),) * 2
        clash = np.linalg.norm(candidates[choice[i], i] - candidates[choice[j], j], axis=1) \
            < (new.radius[i] + new.radius[j]) * (1 - 1e-9)
        if not clash.any():
            break
        later = np.unique(j[clash])
        usable[choice[later], later] = False
        choice[later] = first_usable(usable[:, later])
    keep = np.flatnonzero(choice >= 0)
    placed = NewParticles(candidates[choice[keep], keep], new.v[keep], new.omega[keep], new.radius[keep],
                          new.density[keep], new.motion[keep], new.release_times[keep])
    counts = {"placed": int((choice == 0).sum()), "retried": int((choice > 0).sum()),
              "dropped": int((choice < 0).sum())}
    return Placement(placed, counts)


def first_usable(usable: np.ndarray) -> np.ndarray:
    """(n,) the first row of each column of ``usable`` (attempts, n) that is true, −1 if none."""
    return np.where(usable.any(axis=0), np.argmax(usable, axis=0), -1)


def overlaps(x: np.ndarray, radius: np.ndarray, points: np.ndarray, point_radius: np.ndarray) -> np.ndarray:
    """(m,) whether a sphere at each of ``points`` overlaps one of the spheres (x, radius)."""
    found = kd_tree(x).query_ball_point(points, float(radius.max()) + point_radius)
    sizes = np.fromiter(map(len, found), np.int64, len(found))
    row = np.repeat(np.arange(len(found)), sizes)
    other = np.concatenate([np.asarray(f, np.int64) for f in found]) if sizes.sum() else np.zeros(0, np.int64)
    close = np.linalg.norm(x[other] - points[row], axis=1) < (radius[other] + point_radius[row]) * (1 - 1e-9)
    result = np.zeros(len(points), bool)
    result[row[close]] = True
    return result
