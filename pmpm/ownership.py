"""Particles owned by ranks: the spatial partition, moving rows between ranks, gathering for output.

A particle belongs to the rank whose box holds its centre. In a flow the boxes are the mesh's
(``Mesh.part_boxes``), so the owner holds the particle's centre cell. Without a flow (DEM-only
runs) they are a recursive coordinate bisection of the *particles* (the mesh's own partition balances cells:
in the hopper its cut lies above nearly every particle), planes cutting the longest extent of the
particles' work (``particle_work``: the particle and the contacts it solves) in proportion to the
ranks on each side, computed from histograms summed over ranks (no rank ever holds every
particle), and computed again when the ranks' work drifts apart (``IMBALANCE``). The outer boxes
reach to infinity, so every point has exactly one owner.

Each rank holds its owned particles (sorted by id) and, during a contact step, ghost copies of the
particles of other ranks within a given distance of its box (``pmpm.halo.Halo``): read-only
copies whose velocity changes go back to their owners (``Halo.merge``); in a flow, also ghost
copies of the particles that reach into its cells, whose per-particle sums meet among their
holders (``Halo.sum_over_holders``; ``pmpm.coupling.holders``).
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from mpi4py import MPI
from numba import njit

from .arrays import summed
from .particles import ParticleState

IMBALANCE = 1.02        # the boxes are bisected again when a rank's work is this × the mean (``particle_work``)
CONTACT_WORK, WALL_CONTACT_WORK = 1.0, 3.0   # a remembered contact's work, in particles' (docs/collisions.md)
BINS, ROUNDS = 64, 3    # a cut is placed by ROUNDS histograms of BINS bins (to 1/64³ of the particles' extent)
PARTICLE_FIELDS = tuple(f.name for f in fields(ParticleState))


@dataclass(frozen=True)
class Partition:
    """Each rank's box, [lower, upper) per axis (m); the outer sides at ±inf. (ranks, 3) each."""

    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def whole(cls, ranks: int = 1) -> "Partition":
        """Every point on rank 0 (the boxes of the other ranks empty)."""
        lower, upper = np.full((ranks, 3), np.inf), np.full((ranks, 3), np.inf)
        lower[0], upper[0] = -np.inf, np.inf
        return cls(lower, upper)

    def owner_of(self, x: np.ndarray) -> np.ndarray:
        """(n,) int64, the rank whose box holds each point (n, 3); 0 for a point that is not finite."""
        return _owners(np.ascontiguousarray(x, float).reshape(-1, 3), self.lower, self.upper)

    def distance(self, x: np.ndarray) -> np.ndarray:
        """(n, ranks) distance (m) from each point to each rank's box (0 inside)."""
        return _box_distances(np.ascontiguousarray(x, float).reshape(-1, 3), self.lower, self.upper)

    def to_array(self) -> np.ndarray:
        return np.stack([self.lower, self.upper])

    @classmethod
    def from_array(cls, array: np.ndarray) -> "Partition":
        return cls(np.array(array[0], float), np.array(array[1], float))


@njit(cache=True)
def _owners(x, lower, upper):
    """``Partition.owner_of``, compiled (every step's migration asks it of every particle)."""
    owner = np.zeros(len(x), np.int64)
    for i in range(len(x)):
        for rank in range(len(lower)):
            if (lower[rank, 0] <= x[i, 0] < upper[rank, 0] and lower[rank, 1] <= x[i, 1] < upper[rank, 1]
                    and lower[rank, 2] <= x[i, 2] < upper[rank, 2]):
                owner[i] = rank
                break
    return owner


@njit(cache=True)
def _box_distances(x, lower, upper):
    """``Partition.distance``, compiled."""
    distance = np.zeros((len(x), len(lower)))
    for i in range(len(x)):
        for rank in range(len(lower)):
            distance[i, rank] = box_distance(x[i], lower[rank], upper[rank])
    return distance


@njit(cache=True)
def box_distance(point, lower, upper):
    """The distance (m) from ``point`` (3,) to the box [lower, upper) ((3,) each; 0 inside); a
    coordinate that is not finite adds nothing, an empty box (inf) is at inf. Compiled: the halo
    asks it of the particles near a box's sides every contact step (``pmpm.halo``)."""
    squared = 0.0
    for axis in range(3):
        below, above = lower[axis] - point[axis], point[axis] - upper[axis]
        if below > 0:
            squared += below * below
        elif above > 0:
            squared += above * above
    return np.sqrt(squared)


def bisect(comm, x: np.ndarray, domain: tuple | None = None, work: np.ndarray | None = None) -> Partition:
    """Collective. Boxes that share the particles (centres ``x``, this rank's, (n, 3)) evenly among
    the ranks, by count or by ``work`` (n,) per particle: each box with several ranks is cut across
    the longest extent of its particles, at the share of its ranks on the lower side, level by
    level (one set of reductions per level). A box without particles is cut across the middle of
    its part of ``domain`` ((lower, upper) (3,) each, m; the domain's bounding box), or at 0
    without one."""
    ranks = comm.size
    nodes = [(np.full(3, -np.inf), np.full(3, np.inf), 0, ranks)]   # (lower, upper, first rank, ranks)
    while any(count > 1 for *_, count in nodes):
        split = [k for k, node in enumerate(nodes) if node[3] > 1]
        lower = np.array([nodes[k][0] for k in split])
        upper = np.array([nodes[k][1] for k in split])
        inside = ((x[:, None, :] >= lower[None]) & (x[:, None, :] < upper[None])).all(axis=2)
        node = np.where(inside.any(axis=1), np.argmax(inside, axis=1), -1)
        held = node >= 0
        low = np.full((len(split), 3), np.inf)
        high = np.full((len(split), 3), -np.inf)
        np.minimum.at(low, node[held], x[held])
        np.maximum.at(high, node[held], x[held])
        bounds = np.concatenate([low, -high], axis=1)
        comm.Allreduce(MPI.IN_PLACE, bounds, op=MPI.MIN)
        low, high = bounds[:, :3], -bounds[:, 3:]
        empty = ~np.isfinite(low).all(axis=1)
        low[empty], high[empty] = 0.0, 0.0
        if domain is not None:   # (the domain's part in the box)
            low[empty] = np.clip(domain[0], lower[empty], upper[empty])
            high[empty] = np.clip(domain[1], lower[empty], upper[empty])
        axis = np.argmax(high - low, axis=1)
        share = np.array([(nodes[k][3] // 2) / nodes[k][3] for k in split])
        coordinate = np.where(held, x[np.arange(len(x)), axis[np.maximum(node, 0)]] if len(x) else 0.0, 0.0)
        cut = quantile_cut(comm, coordinate, node, low[np.arange(len(split)), axis],
                           high[np.arange(len(split)), axis], share, work)
        children = []
        for k, (lo, hi, first, count) in enumerate(nodes):
            if count == 1:
                children.append(nodes[k])
                continue
            s = split.index(k)
            left = count // 2
            upper_left, lower_right = hi.copy(), lo.copy()
            upper_left[axis[s]] = lower_right[axis[s]] = np.clip(cut[s], lo[axis[s]], hi[axis[s]])
            children += [(lo, upper_left, first, left), (lower_right, hi, first + left, count - left)]
        nodes = children
    nodes.sort(key=lambda node: node[2])
    return Partition(np.array([node[0] for node in nodes]), np.array([node[1] for node in nodes]))


def quantile_cut(comm, coordinate: np.ndarray, node: np.ndarray, low: np.ndarray, high: np.ndarray,
                 share: np.ndarray, work: np.ndarray | None = None) -> np.ndarray:
    """Collective. Per node, a coordinate below which ``share`` of its particles lie, or of their
    ``work`` (``coordinate``, ``node`` and ``work`` per particle, node −1: in none), narrowed by
    ROUNDS histograms summed over ranks; the midpoint of [low, high] for a node without particles."""
    nodes = len(low)
    held = node >= 0
    work = np.ones(len(node)) if work is None else np.asarray(work, float)
    lo, hi = low.astype(float).copy(), high.astype(float).copy()
    below = np.zeros(nodes)                       # the work below lo, per node
    total = summed(node[held], work[held], nodes)
    comm.Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
    target = share * total
    for _ in range(ROUNDS):
        width = np.maximum(hi - lo, 1e-300)
        b = np.floor((coordinate[held] - lo[node[held]]) / width[node[held]] * BINS).astype(np.int64)
        inside = (b >= 0) & (b < BINS)
        counts = summed(node[held][inside] * BINS + b[inside], work[held][inside], nodes * BINS)
        comm.Allreduce(MPI.IN_PLACE, counts, op=MPI.SUM)
        running = below[:, None] + np.cumsum(counts.reshape(nodes, BINS), axis=1)
        k = np.minimum((running < target[:, None]).sum(axis=1), BINS - 1)   # the bin where the share is reached
        below = np.where(k > 0, running[np.arange(nodes), np.maximum(k - 1, 0)], below)
        lo, hi = lo + width * k / BINS, lo + width * (k + 1) / BINS
    return np.where(total > 0, hi, 0.5 * (low + high))


def particle_work(ids: np.ndarray, first_id: np.ndarray, second_id: np.ndarray) -> np.ndarray:
    """(n,) each particle's share of a contact step's work, in units of a particle without
    contacts: 1 + ``CONTACT_WORK`` per remembered contact with another particle and
    ``WALL_CONTACT_WORK`` per one with a wall, counted on the particle that solves it (the
    contact's lower-id one: ``first_id``; ``second_id`` < 0 for a wall; both sorted by first_id).
    ``ids`` (n,) sorted. The lower box of a hopper has more contacts per particle, and its cone's
    wall contacts, which the wall search, the narrow phase and the sweeps all pay for."""
    work = np.ones(len(ids))
    for cost, rows in ((CONTACT_WORK, second_id >= 0), (WALL_CONTACT_WORK, second_id < 0)):
        first = first_id[rows]
        work += cost * (np.searchsorted(first, ids, "right") - np.searchsorted(first, ids, "left"))
    return work


def rank_work(particles: int, second_id: np.ndarray) -> float:
    """``particle_work`` summed over a rank's ``particles`` (a count), whose remembered contacts have
    ``second_id`` (< 0 for a wall): the rebalancing test, without a pass over the particles."""
    walls = int((second_id < 0).sum())
    return particles + CONTACT_WORK * (len(second_id) - walls) + WALL_CONTACT_WORK * walls


# ----------------------------------------------------------------------------------------------
# Colours, and rows for output (``pmpm.packed`` moves rows between ranks)
# ----------------------------------------------------------------------------------------------
def greedy_colours(neighbours: list) -> np.ndarray:
    """(ranks,) a colour per rank, greedy in rank order, apart from every rank it lists as a
    neighbour or that lists it (``neighbours``: per rank, the ranks it holds a particle with)."""
    colour = np.zeros(len(neighbours), np.int64)
    for rank in range(len(neighbours)):
        taken = {int(colour[other]) for other in neighbours[rank] if other < rank}
        taken |= {int(colour[other]) for other in range(rank) if rank in neighbours[other]}
        colour[rank] = min(set(range(len(taken) + 1)) - taken)
    return colour


def particle_rows(particles: ParticleState, rows: np.ndarray | None = None) -> dict:
    """The particles' fields by name: every row (the arrays themselves), or the rows ``rows``
    (indices; take: a third of the time of fancy indexing on rows of (n, 3))."""
    if rows is None:
        return {name: getattr(particles, name) for name in PARTICLE_FIELDS}
    return {name: getattr(particles, name).take(rows, axis=0) for name in PARTICLE_FIELDS}


def gather(comm, particles: ParticleState) -> ParticleState:
    """Collective. Every rank's particles on every rank, sorted by id (for output and checkpoints)."""
    return gather_with(comm, particles)[0]


def gather_with(comm, particles: ParticleState, *arrays: np.ndarray) -> tuple:
    """Collective. ``gather``, and ``arrays`` with a row per particle gathered in the same order."""
    if comm.size == 1:
        return (particles, *arrays)
    parts = comm.allgather((particle_rows(particles), arrays))
    rows = {name: np.concatenate([part[name] for part, _ in parts]) for name in PARTICLE_FIELDS}
    order = np.argsort(rows["id"], kind="stable")
    joined = [np.concatenate([extra[k] for _, extra in parts])[order] for k in range(len(arrays))]
    return (ParticleState(**{name: values[order] for name, values in rows.items()}), *joined)
