"""Ghost copies: the particles of other ranks that one rank holds during a contact step, and the
exchanges between the ranks that hold a particle together (``pmpm.ownership`` has the ranks'
boxes, ``pmpm.packed`` the rows that move between them)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from mpi4py import MPI
from numba import njit

from .ownership import Partition, box_distance, greedy_colours
from .packed import FIELD_COLUMNS, X, exchanged, merged, packed
from .particles import ParticleState


class Pass(NamedTuple):
    """The local rows of the particles this rank and one other hold together that pass between
    them in the block sweeps (``Halo.passes``)."""

    sweep: np.ndarray            # both ranks change them: sent and received after each sweep
    sent_after: np.ndarray       # only this rank changes them: sent once, after the last sweep
    received_after: np.ndarray   # only the other changes them: received then


@dataclass
class Halo:
    """The ghost copies of one contact step on this rank (local rows: owned and ghost particles
    together, sorted by id).

    owned : (n_local,) bool; send : per neighbour rank, the local rows of owned particles it holds
    as ghosts; receive : per neighbour rank, the local rows of its particles held here;
    shared_rows : the local rows of the particles another rank holds too (owned or ghost on
    either), sorted; shared_at : per such rank, the positions in ``shared_rows`` of the particles
    both hold, by id.

    Notes
    -----
    ``to_ghosts`` copies owners' rows to their ghosts, ``to_owners`` adds the ghosts' rows to their
    owners' (and zeroes them): one message each way per neighbour, none between ranks that share
    no ghost. ``merge`` takes one message each way between ranks that hold a particle together:
    each holder sends its change to the others, and all add the changes in rank order.
    ``passes`` agrees, once per step, which shared rows the block Gauss–Seidel's sweeps pass on from
    one rank to the next in the order of ``colours`` (``collisions.block``, compiled with its
    messages): after each sweep those both ranks change, after the last the rows only the sender
    changes.
    """

    comm: object
    owned: np.ndarray
    send: dict
    receive: dict
    shared_rows: np.ndarray
    shared_at: dict
    sent: int = 0          # bytes this rank has sent, the ghosts included

    @classmethod
    def build(cls, comm, partition: Partition, particles: ParticleState, width: np.ndarray | float):
        """Collective. The ghosts of every rank's ``particles`` (owned), sent to each rank whose box
        lies within ``width`` (m; per particle, or one value) of the centre. Returns the halo and
        the local particles (owned and ghosts, sorted by id)."""
        width = np.ascontiguousarray(np.broadcast_to(np.asarray(width, float), (len(particles),)))
        rank, sources = _ghosts_sent(np.ascontiguousarray(particles.x, float), width, partition.lower,
                                     partition.upper, comm.rank)   # grouped by rank, by id within each
        block = packed(particles, sources, width)   # (with the width: the receiver finds the holders)
        [(arrived, offsets)] = exchanged(comm, (rank, block))
        local, where, ghost_rows, _ = merged(particles, arrived)
        owned = np.zeros(len(local), bool)
        owned[where] = True
        edges = np.searchsorted(rank, np.arange(comm.size + 1))
        send = {int(r): where[sources[edges[r]:edges[r + 1]]] for r in np.flatnonzero(np.diff(edges))}
        receive = {int(r): ghost_rows[offsets[r]:offsets[r + 1]] for r in np.flatnonzero(np.diff(offsets))}
        # who holds what together: an owned particle with the ranks it went to; a ghost with every
        # rank its owner sent it to (the same test on the same bits) and its owner
        ghost, other = _holders(arrived, offsets, partition.lower, partition.upper, comm.rank)
        shared_rows, at, edges = _shared(len(local), np.concatenate([where[sources], ghost_rows[ghost]]),
                                         np.concatenate([rank, other]), comm.size)
        shared_at = {int(r): at[edges[r]:edges[r + 1]] for r in np.flatnonzero(np.diff(edges))}
        return cls(comm, owned, send, receive, shared_rows, shared_at, block.nbytes), local

    def _swap(self, outgoing: dict, incoming: dict, arrays: tuple, combine) -> None:
        """Send each array's rows ``outgoing[r]`` to each r, the arrays side by side in one message;
        each received block goes to the arrays' rows ``incoming[r]`` by ``combine``. The arrays
        (a row per local particle) share one dtype."""
        if len({array.dtype for array in arrays}) > 1:
            raise ValueError("Halo exchanges arrays of one dtype at a time")
        widths = np.cumsum([0] + [math.prod(array.shape[1:]) for array in arrays])
        requests, buffers = [], {}
        for r, rows in incoming.items():
            buffers[r] = np.empty((len(rows), widths[-1]), arrays[0].dtype)
            requests.append(self.comm.Irecv(buffers[r], source=r, tag=77))
        blocks = [np.concatenate([array[rows].reshape(len(rows), -1) for array in arrays], axis=1)
                  for rows in outgoing.values()]
        requests += [self.comm.Isend(block, dest=r, tag=77) for r, block in zip(outgoing, blocks)]
        self.sent += sum(block.nbytes for block in blocks)
        MPI.Request.Waitall(requests)
        for r, rows in incoming.items():
            for array, begin, end in zip(arrays, widths[:-1], widths[1:]):
                combine(array, rows, buffers[r][:, begin:end].reshape((len(rows),) + array.shape[1:]))

    def to_ghosts(self, *arrays: np.ndarray) -> None:
        """Collective. Each ghost row takes its owner's value, in place (the arrays share a dtype)."""
        self._swap(self.send, self.receive, arrays, _assign)

    def to_owners(self, *arrays: np.ndarray) -> None:
        """Collective. Each ghost row is added to its owner's row and set to zero, in place (the
        arrays share a dtype)."""
        self._swap(self.receive, self.send, arrays, _add)
        for array in arrays:
            for rows in self.receive.values():
                array[rows] = 0

    def sum_over_holders(self, array: np.ndarray) -> np.ndarray:
        """Collective. ``array`` (a row per local particle) with each row the sum of the rows of every
        rank that holds the particle, on each of them (ghosts added to their owner, then copied back)."""
        self.to_owners(array)
        self.to_ghosts(array)
        return array

    def max_over_holders(self, array: np.ndarray) -> np.ndarray:
        """Collective. As ``sum_over_holders``, the largest instead of the sum."""
        self._swap(self.receive, self.send, (array,), _maximum)
        self.to_ghosts(array)
        return array

    def colours(self) -> np.ndarray:
        """Collective. (comm.size,) a colour per rank, ranks holding a particle together coloured
        apart (``greedy_colours``), the same on every rank. Two ranks: 0 and 1, without a message."""
        if self.comm.size == 2:
            return np.arange(2)
        return greedy_colours(self.comm.allgather(sorted(self.shared_at)))

    def passes(self, ranks, changing: np.ndarray) -> dict:
        """Collective among ``ranks`` (those this rank shares particles with). Per rank r of them,
        the ``Pass`` of the particles both hold: each sweep, the rows ``changing`` (bool per local
        row) on both ranks; after the last, the rows changing on the sender only (the receiver's
        sweeps never read them). One message each way."""
        rows = {r: self.shared_rows[self.shared_at[r]] for r in ranks}
        masks = {r: changing[rows[r]].astype(np.uint8) for r in ranks}
        theirs = {r: np.empty_like(mask) for r, mask in masks.items()}
        requests = [self.comm.Irecv(theirs[r], source=r, tag=80) for r in ranks]
        requests += [self.comm.Isend(masks[r], dest=r, tag=80) for r in ranks]
        MPI.Request.Waitall(requests)
        passes = {}
        for r in ranks:
            mine, other = masks[r] > 0, theirs[r] > 0
            passes[r] = Pass(rows[r][mine & other], rows[r][mine & ~other], rows[r][other & ~mine])
        return passes

    def merge(self, reference: tuple, *arrays: np.ndarray) -> None:
        """Collective. Copies of particles changed by the ranks that hold them: each holder's change
        since ``reference`` (the arrays as they were at the last merge, the same on every holder) is
        sent to the other holders, and every holder sets reference + the changes of all, added in
        rank order (so the copies stay equal to the bit); the reference arrays' shared rows take the
        merged values. Rows held here only are left as they are, in both. It touches the shared rows
        only (the warm start of the block Gauss–Seidel: each rank's remembered impulses summed)."""
        rows = self.shared_rows
        if len(rows) == 0:
            return
        arrays, reference = tuple(arrays), tuple(reference)
        if not all(a.ndim == 2 and a.flags.c_contiguous for a in arrays + reference):
            raise ValueError("Halo.merge takes C-contiguous 2-D arrays")
        change = _rows_of(rows, arrays) - _rows_of(rows, reference)
        # the other holders' changes in one buffer, in rank order (the lower ranks' rows first)
        neighbours = sorted(self.shared_at)
        at = [self.shared_at[r] for r in neighbours]
        edges = np.cumsum([0] + [len(positions) for positions in at])
        received = np.empty((edges[-1], change.shape[1]))
        requests = [self.comm.Irecv(received[edges[k]:edges[k + 1]], source=r, tag=78)
                    for k, r in enumerate(neighbours)]
        # a neighbour holding every shared row (two ranks: always) takes the changes as they are
        outgoing = [change if len(positions) == len(rows) else np.ascontiguousarray(change[positions])
                    for positions in at]
        requests += [self.comm.Isend(block, dest=r, tag=78) for r, block in zip(neighbours, outgoing)]
        self.sent += sum(block.nbytes for block in outgoing)
        MPI.Request.Waitall(requests)
        below = int(edges[np.searchsorted(neighbours, self.comm.rank)])
        positions = np.concatenate([np.zeros(0, np.int64), *at])
        _apply_merged(rows, arrays, reference, change, received, positions, below)


@njit(cache=True)
def _ghosts_sent(x, width, lower, upper, me):
    """The ghosts rank ``me`` sends: (ranks, rows) of its particles (centres x (n, 3)) within
    ``width`` (n,) of another rank's box (``lower``, ``upper``: (ranks, 3) each), grouped by rank,
    by row within each (a particle near a corner goes to several). Only the particles nearer than
    their width to a side of this rank's box are measured against the others'."""
    n, ranks = len(x), len(lower)
    near = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        depth = np.inf
        for d in range(3):
            depth = min(depth, x[i, d] - lower[me, d], upper[me, d] - x[i, d])
        if depth < width[i]:
            near[m] = i
            m += 1
    sent_to = np.zeros((m, ranks), np.bool_)   # (near particle, rank): within its width of that box
    count = np.zeros(ranks + 1, np.int64)
    for k in range(m):
        i = near[k]
        for r in range(ranks):
            if r != me and box_distance(x[i], lower[r], upper[r]) < width[i]:
                sent_to[k, r] = True
                count[r + 1] += 1
    for r in range(ranks):
        count[r + 1] += count[r]
    rank, rows = np.empty(count[ranks], np.int64), np.empty(count[ranks], np.int64)
    for k in range(m):
        for r in range(ranks):
            if sent_to[k, r]:
                rank[count[r]], rows[count[r]] = r, near[k]
                count[r] += 1
    return rank, rows


@njit(cache=True)
def _holders(arrived, offsets, lower, upper, me):
    """The other ranks that hold each ghost that arrived here (``arrived``'s rows, rank r's from
    ``offsets[r]``, its width after its fields): its owner, and every rank its owner sent it to
    (the owner's test, on the same bits). (ghost rows, ranks), by row, by rank within each."""
    ranks = len(lower)
    ghost, other = np.empty(len(arrived) * ranks, np.int64), np.empty(len(arrived) * ranks, np.int64)
    k = 0
    for owner in range(ranks):
        for g in range(offsets[owner], offsets[owner + 1]):
            for r in range(ranks):
                if r != me and (r == owner or box_distance(arrived[g, X:X + 3], lower[r], upper[r])
                                < arrived[g, FIELD_COLUMNS]):
                    ghost[k], other[k] = g, r
                    k += 1
    return ghost[:k], other[:k]


@njit(cache=True)
def _shared(n, local_row, other, ranks):
    """From each (local row, other rank holding that particle too) of ``local_row``, ``other``: the
    shared rows (sorted), and per rank the positions in them of the rows it holds too, ascending
    (all ranks' one after another, rank r's from ``edges[r]``)."""
    shared = np.zeros(n, np.bool_)
    for k in range(len(local_row)):
        shared[local_row[k]] = True
    position = np.full(n, -1, np.int64)    # a shared row's place in shared_rows
    count = 0
    for i in range(n):
        if shared[i]:
            position[i] = count
            count += 1
    shared_rows = np.flatnonzero(shared)
    edges = np.zeros(ranks + 1, np.int64)
    for k in range(len(other)):
        edges[other[k] + 1] += 1
    for r in range(ranks):
        edges[r + 1] += edges[r]
    at, fill = np.empty(len(other), np.int64), edges[:ranks].copy()
    for k in range(len(other)):
        at[fill[other[k]]] = position[local_row[k]]
        fill[other[k]] += 1
    for r in range(ranks):
        at[edges[r]:edges[r + 1]] = np.sort(at[edges[r]:edges[r + 1]])
    return shared_rows, at, edges


@njit(cache=True)
def _rows_of(rows, arrays):
    """(len(rows), Σ widths): the arrays' ``rows`` side by side."""
    width = 0
    for k in range(len(arrays)):
        width += arrays[k].shape[1]
    out = np.empty((len(rows), width))
    column = 0
    for k in range(len(arrays)):
        for i in range(len(rows)):
            for j in range(arrays[k].shape[1]):
                out[i, column + j] = arrays[k][rows[i], j]
        column += arrays[k].shape[1]
    return out


@njit(cache=True)
def _apply_merged(rows, arrays, reference, change, received, at, below):
    """Each array and its reference set, on ``rows``, to reference + the sum of every holder's
    change. The sum is taken in rank order, so that every holder gets the same bits: the
    ``received`` rows (at positions ``at`` of ``rows``) of lower ranks (the first ``below``), this
    rank's ``change``, then the higher ranks'."""
    total = np.zeros_like(change)
    width = change.shape[1]
    for i in range(below):
        for j in range(width):
            total[at[i], j] += received[i, j]
    for i in range(len(change)):
        for j in range(width):
            total[i, j] += change[i, j]
    for i in range(below, len(at)):
        for j in range(width):
            total[at[i], j] += received[i, j]
    column = 0
    for k in range(len(arrays)):
        now, before = arrays[k], reference[k]
        for i in range(len(rows)):
            r = rows[i]
            for j in range(now.shape[1]):
                now[r, j] = before[r, j] = before[r, j] + total[i, column + j]
        column += now.shape[1]


def _assign(array, rows, values):
    array[rows] = values


def _maximum(array, rows, values):
    array[rows] = np.maximum(array[rows], values)


def _add(array, rows, values):
    array[rows] += values   # (a rank's rows are distinct: no np.add.at needed)
