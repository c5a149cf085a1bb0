"""Particle rows as one block of float64 columns: what moves between ranks (ghosts, migration, the
particles a gathered contact step takes on every rank).

A ``ParticleState``'s fields are a dozen arrays; moving some rows of each to another rank took a
take, a message part and a join per field. Here the rows are packed side by side in one compiled
pass, sent as one buffer per rank pair (``exchanged``) or to every rank (``gathered``), and merged
into the receiver's rows (sorted by id) in one compiled pass. Ids, motion codes and deposition
flags travel as float64 (ids exact below 2^53).
"""
from __future__ import annotations

import numpy as np
from mpi4py import MPI
from numba import njit

from .particles import ParticleState

ID, X, V, OMEGA, RADIUS, DENSITY, MOTION, DEPOSITED = 0, 1, 4, 7, 10, 11, 12, 13
FIELD_COLUMNS = 14   # the columns of a ParticleState's row; extra columns follow


def packed(particles: ParticleState, rows: np.ndarray, *extra: np.ndarray) -> np.ndarray:
    """(len(rows), FIELD_COLUMNS + extra columns) the particles' ``rows`` (indices), with the same
    rows of each of ``extra`` (float64, (n,) or (n, k)) after their fields."""
    columns = [values[:, None] if values.ndim == 1 else values for values in map(np.asarray, extra)]
    out = np.empty((len(rows), FIELD_COLUMNS + sum(values.shape[1] for values in columns)))
    _pack(np.asarray(rows, np.int64), particles.id, particles.x, particles.v, particles.omega, particles.radius,
          particles.density, particles.motion, particles.deposited, out)
    column = FIELD_COLUMNS
    for values in columns:
        out[:, column:column + values.shape[1]] = values[rows]
        column += values.shape[1]
    return out


def merged(particles: ParticleState, block: np.ndarray, keep: np.ndarray | None = None,
           extra: tuple = ()) -> tuple:
    """``particles`` (sorted by id; ``keep``: those where true) and the rows of ``block`` (other
    ids, any order) in one state sorted by id; with the row in it of each of ``particles`` (−1: not
    kept) and of each of ``block``'s rows; and the arrays ``extra`` ((n, 3) each: a row per
    particle, the block's rows holding theirs after their fields, in order) merged alike."""
    order = np.argsort(block[:, ID], kind="stable")
    keep = np.ones(len(particles), bool) if keep is None else keep
    # (the kernel takes a tuple of at least one array: an empty one stands in where there are none)
    *fields, merged_extra, where_own, where_block = _merge(
        particles.id, particles.x, particles.v, particles.omega, particles.radius, particles.density,
        particles.motion, particles.deposited, keep, tuple(extra) or (np.empty((0, 3)),), block, order, len(extra))
    return ParticleState(*fields), where_own, where_block, merged_extra[:len(extra)]


def exchanged(comm, *groups: tuple) -> list[tuple[np.ndarray, np.ndarray]]:
    """Collective. Per group (destination, block): each row of ``block`` to rank ``destination``
    (−1: nowhere); returns per group the rows received, in rank order (each rank's in the order
    it sent them), and where each rank's begin ((size + 1,) offsets). One exchange of counts for
    all groups, one of rows per group; a group's blocks have the same width on every rank."""
    counts = np.empty((comm.size, len(groups)), np.int64)
    sent, starts = [], []
    for g, (destination, block) in enumerate(groups):
        order, bounds = _by_rank(destination, comm.size)
        sent.append(block[order])
        counts[:, g] = bounds[1:] - bounds[:-1]
        starts.append(bounds[:-1])
    arriving = np.empty_like(counts)
    comm.Alltoall(counts, arriving)
    offsets = _offsets(arriving)
    result = []
    for g, block in enumerate(sent):
        width = block.shape[1]
        received = np.empty((int(offsets[-1, g]), width))
        comm.Alltoallv([block, counts[:, g] * width, starts[g] * width, MPI.DOUBLE],
                       [received, arriving[:, g] * width, offsets[:-1, g] * width, MPI.DOUBLE])
        result.append((received, offsets[:, g].copy()))
    return result


def gathered(comm, *blocks: np.ndarray) -> list[np.ndarray]:
    """Collective. Per block (float64 rows; a block's width the same on every rank): every rank's
    rows on every rank, in rank order. One gather of counts for all, one of rows per block."""
    counts = np.empty((comm.size, len(blocks)), np.int64)
    comm.Allgather(np.array([len(block) for block in blocks], np.int64), counts)
    offsets = _offsets(counts)
    result = []
    for g, block in enumerate(blocks):
        width = block.shape[1]
        received = np.empty((int(offsets[-1, g]), width))
        comm.Allgatherv(np.ascontiguousarray(block, float),
                        [received, counts[:, g] * width, offsets[:-1, g] * width, MPI.DOUBLE])
        result.append(received)
    return result


def _offsets(counts: np.ndarray) -> np.ndarray:
    """(ranks + 1, groups): where each rank's rows begin among those received, per group (the
    total last), from the counts (ranks, groups)."""
    offsets = np.zeros((len(counts) + 1, counts.shape[1]), np.int64)
    np.cumsum(counts, axis=0, out=offsets[1:])
    return offsets


@njit(cache=True)
def _by_rank(destination, ranks):
    """The rows with a destination rank (>= 0), grouped by it in their order (a stable counting
    sort), and where each rank's begin ((ranks + 1,) bounds)."""
    bounds = np.zeros(ranks + 1, np.int64)
    for d in destination:
        if d >= 0:
            bounds[d + 1] += 1
    for r in range(ranks):
        bounds[r + 1] += bounds[r]
    order, fill = np.empty(bounds[ranks], np.int64), bounds[:ranks].copy()
    for i in range(len(destination)):
        if destination[i] >= 0:
            order[fill[destination[i]]] = i
            fill[destination[i]] += 1
    return order, bounds


@njit(cache=True)
def _pack(rows, pid, x, v, omega, radius, density, motion, deposited, out):
    for k in range(len(rows)):
        i = rows[k]
        out[k, ID] = pid[i]
        for d in range(3):
            out[k, X + d] = x[i, d]
            out[k, V + d] = v[i, d]
            out[k, OMEGA + d] = omega[i, d]
        out[k, RADIUS] = radius[i]
        out[k, DENSITY] = density[i]
        out[k, MOTION] = motion[i]
        out[k, DEPOSITED] = 1.0 if deposited[i] else 0.0


@njit(cache=True)
def _merge(pid, x, v, omega, radius, density, motion, deposited, keep, extra, block, order, n_extra):
    """The two sorted sequences (the rows where ``keep``, and the block's rows in ``order``) merged
    by id: the fields of a ``ParticleState``, the first ``n_extra`` of ``extra`` ((n, 3) arrays)
    merged alike, and each one's row in the result (where_own −1: not kept)."""
    n, m = len(pid), len(order)
    total = m
    for i in range(n):
        total += keep[i]
    out_id, out_radius, out_density = np.empty(total, np.int64), np.empty(total), np.empty(total)
    out_x, out_v, out_omega = np.empty((total, 3)), np.empty((total, 3)), np.empty((total, 3))
    out_motion, out_deposited = np.empty(total, np.int8), np.empty(total, np.bool_)
    out_extra = [np.empty((total if n_extra else 0, 3)) for _ in range(max(n_extra, 1))]   # (one empty: none)
    where_own, where_block = np.full(n, -1, np.int64), np.empty(m, np.int64)
    i, j, k = 0, 0, 0
    while i < n or j < m:
        if i < n and not keep[i]:
            i += 1
            continue
        if j == m or (i < n and pid[i] < np.int64(block[order[j], ID])):
            out_id[k] = pid[i]
            for d in range(3):
                out_x[k, d], out_v[k, d], out_omega[k, d] = x[i, d], v[i, d], omega[i, d]
            out_radius[k], out_density[k] = radius[i], density[i]
            out_motion[k], out_deposited[k] = motion[i], deposited[i]
            for e in range(n_extra):
                for d in range(3):
                    out_extra[e][k, d] = extra[e][i, d]
            where_own[i] = k
            i += 1
        else:
            a = order[j]
            out_id[k] = np.int64(block[a, ID])
            for d in range(3):
                out_x[k, d], out_v[k, d] = block[a, X + d], block[a, V + d]
                out_omega[k, d] = block[a, OMEGA + d]
            out_radius[k], out_density[k] = block[a, RADIUS], block[a, DENSITY]
            out_motion[k], out_deposited[k] = np.int8(block[a, MOTION]), block[a, DEPOSITED] > 0
            for e in range(n_extra):
                for d in range(3):
                    out_extra[e][k, d] = block[a, FIELD_COLUMNS + 3 * e + d]
            where_block[a] = k
            j += 1
        k += 1
    return (out_id, out_x, out_v, out_omega, out_radius, out_density, out_motion, out_deposited, out_extra, where_own,
            where_block)
